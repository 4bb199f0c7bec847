"""A session recorded to MCAP by the service: the demo's recording opens with the mcap reader, its
ROS 2 channels decode with rosbags, and `inhand-tracker replay` tracks it again to the same
estimates on the CPU."""

from __future__ import annotations

import json

import numpy as np
from mcap.reader import make_reader
from service_process import ServiceProcess, free_port
from typer.testing import CliRunner

from client import TrackerClient
from protocol import CHANNELS, SessionRecording, Trajectory
from service.cli import app
from service.paths import DATA_DIR

TRAJECTORY = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"


def test_the_demo_s_recording_opens_in_mcap_and_replays_to_the_same_estimates(tmp_path):
    from rosbags.typesys import Stores, get_typestore

    out = CliRunner().invoke(app, ["demo", "--device", "cpu", "--worlds", "8", "--record", str(tmp_path)])
    assert out.exit_code == 0, out.output[-3000:]
    (path,) = tmp_path.glob("*.mcap")
    traj = Trajectory.load(TRAJECTORY)

    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == set(CHANNELS.values())
        counts = {summary.channels[i].topic: n for i, n in summary.statistics.channel_message_counts.items()}
        for role in ("frame", "estimate", "population", "joint_states", "pose", "tf"):
            assert counts[CHANNELS[role]] == traj.frames, (role, counts)
        schema = summary.schemas[topics[CHANNELS["pose"]].schema_id]
        assert (schema.name, schema.encoding) == ("geometry_msgs/msg/PoseWithCovarianceStamped", "ros2msg")
        store = get_typestore(Stores.ROS2_JAZZY)
        poses, estimates = [], []
        for _, channel, message in reader.iter_messages(topics=[CHANNELS["pose"], CHANNELS["estimate"]]):
            if channel.topic == CHANNELS["pose"]:
                poses.append(store.deserialize_cdr(message.data, "geometry_msgs/msg/PoseWithCovarianceStamped"))
            else:
                estimates.append(json.loads(message.data))
    p = poses[-1].pose.pose
    np.testing.assert_allclose([p.position.x, p.position.y, p.position.z], estimates[-1]["pose"][:3], atol=1e-7)

    recording = SessionRecording.load(path)
    assert recording.opened["worlds"] == 8 and recording.opened["object"] == traj.object
    for name, sent in traj.sensing.items():
        kept = recording.trajectory.sensing[name]
        assert (sent is None) == (kept is None), name
        if sent is not None:
            np.testing.assert_array_equal(kept, sent, err_msg=name)  # exactly what the robot sent
    assert [e.seq for e in recording.estimates] == list(range(traj.frames))

    svc = ServiceProcess(free_port())
    try:
        with TrackerClient(connect=[svc.endpoint]) as probe:
            svc.wait_ready(probe)
        out = CliRunner().invoke(app, ["replay", str(path), "--connect", svc.endpoint])
    finally:
        svc.stop()
    assert out.exit_code == 0, out.output[-3000:]
    assert f"against the recording: {traj.frames} estimates, position differs by at most 0.000 mm" in out.output
