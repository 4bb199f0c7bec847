"""A session recorded to MCAP by the service: the demo's recording opens with the mcap reader, its
ROS 2 channels decode with rosbags, and `inhand-tracker replay` tracks it again to the same
estimates on the CPU."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from service_process import ServiceProcess, free_port
from typer.testing import CliRunner

from inhand_tracker.client import TrackerClient
from inhand_tracker.protocol import CHANNELS, SessionRecording, Trajectory
from inhand_tracker.service.cli import app
from inhand_tracker.service.paths import DATA_DIR

TRAJECTORY = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"


def test_the_demo_s_recording_is_a_rosbag2_folder_and_replays_to_the_same_estimates(tmp_path):
    """rosbags opens the recording's folder as a rosbag2 bag (its metadata.yaml, MCAP storage) and
    decodes every message of every channel from the schemas in the file alone; the light client
    replays it."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Reader

    out = CliRunner().invoke(app, ["demo", "--device", "cpu", "--worlds", "8", "--record", str(tmp_path)])
    assert out.exit_code == 0, out.output[-3000:]
    (folder,) = tmp_path.iterdir()
    (path,) = folder.glob("*.mcap")
    traj = Trajectory.load(TRAJECTORY)
    assert folder.name.startswith("allegro_foam_brick_") and path.name == f"{folder.name}_0.mcap"
    with Reader(folder) as bag:  # the folder reader: metadata.yaml first
        assert bag.message_count == sum(c.msgcount for c in bag.connections) == 6 * traj.frames  # no observations
        assert {c.topic for c in bag.connections} == set(CHANNELS.values())
        assert {c.topic: c.msgcount for c in bag.connections}[CHANNELS["frame"]] == traj.frames

    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == set(CHANNELS.values())
        counts = {summary.channels[i].topic: n for i, n in summary.statistics.channel_message_counts.items()}
        for role in ("frame", "estimate", "population", "joint_states", "pose", "tf"):
            assert counts[CHANNELS[role]] == traj.frames, (role, counts)
        assert reader.get_header().profile == "ros2"
        schema = summary.schemas[topics[CHANNELS["pose"]].schema_id]
        assert (schema.name, schema.encoding) == ("geometry_msgs/msg/PoseWithCovarianceStamped", "ros2msg")
        frame = summary.schemas[topics[CHANNELS["frame"]].schema_id].data.decode()
        assert "float32[] q  # Measured joint positions. Shape ('D',) [rad or m]." in frame.splitlines(), frame
        assert "float64 stamp  # Robot clock when the frame was sensed [s]" in frame, frame
        assert {(c.message_encoding, summary.schemas[c.schema_id].encoding) for c in topics.values()} == {
            ("cdr", "ros2msg")
        }
    with AnyReader([folder]) as bag:  # its types from the file's schemas, not from this project
        decoded = {
            c.topic: [bag.deserialize(raw, c.msgtype) for c, _, raw in bag.messages([c])] for c in bag.connections
        }
    assert {t: len(m) for t, m in decoded.items() if m} == {t: n for t, n in counts.items() if n}
    p, estimate = decoded[CHANNELS["pose"]][-1].pose.pose, decoded[CHANNELS["estimate"]][-1]
    np.testing.assert_allclose([p.position.x, p.position.y, p.position.z], estimate.pose[:3], atol=1e-7)
    first = decoded[CHANNELS["frame"]][0]
    assert first.q.shape == (traj.q.shape[1],) and first.has_force == (traj.force is not None) and not first.has_touch

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
        out = CliRunner().invoke(app, ["replay", str(folder), "--connect", svc.endpoint])
    finally:
        svc.stop()
    assert out.exit_code == 0, out.output[-3000:]
    assert f"against the recording: {traj.frames} estimates, position differs by at most 0.000 mm" in out.output


def _session(traj: Trajectory, session: str = "0a1b2c3d4e5f"):
    from inhand_tracker.protocol import OpenSession, SessionInfo

    request = OpenSession(robot=traj.robot, object=traj.object, p0=traj.truth.initial_pose, worlds=8)
    info = SessionInfo(session=session, token="t", robot=traj.robot, object=traj.object,
                       joint_names=[f"j{i}" for i in range(traj.controls.shape[1])], sensor_names=["a", "b", "c", "d"],
                       worlds=8, method="PBO", name="left_hand")  # fmt: skip
    return info, request


def test_every_channel_carries_its_full_schema_and_a_killed_service_leaves_a_readable_file(tmp_path):
    """Recorded for over a second and never closed (as after kill -9): the chunks flushed each
    second read back; every channel's ROS 2 schema lists its message's fields."""
    import time

    from mcap.data_stream import EndOfFile
    from mcap.records import Message, Schema
    from mcap.stream_reader import StreamReader

    from inhand_tracker.service.server.recording import SessionRecorder

    traj = Trajectory.load(TRAJECTORY)
    info, request = _session(traj)
    recorder = SessionRecorder(tmp_path, "default")
    recorder.open(info, request)
    began = time.monotonic()
    i = 0
    while time.monotonic() - began < 1.5:
        recorder.frame(traj.frame(i % traj.frames, info.session))
        i += 1
        time.sleep(0.01)
    (path,) = tmp_path.glob("*/*.mcap")  # not closed: the footer and summary are missing
    records = []
    with contextlib.suppress(EndOfFile):  # the file ends mid-record, where the process stopped
        records.extend(StreamReader(path.open("rb"), skip_magic=False).records)
    schemas = {r.name: r.data.decode() for r in records if isinstance(r, Schema)}
    assert {r.encoding for r in records if isinstance(r, Schema)} == {"ros2msg"}

    def fields(name: str) -> set[str]:  # the message's own fields: its definition before its dependencies'
        own = schemas[name].split("\n=")[0].splitlines()
        return {line.split()[1] for line in own if line and line[0] != "#"}

    frame, estimate = fields("inhand_tracker/msg/RobotFrame"), fields("inhand_tracker/msg/Estimate")
    assert {"q", "controls", "force", "has_force", "touch", "stamp"} <= frame and not {"token", "mac"} & frame
    assert {"pose", "covariance", "status", "mass", "friction"} <= estimate
    assert {
        "inhand_tracker/msg/PoseObservation",
        "inhand_tracker/msg/PopulationSummary",
        "tf2_msgs/msg/TFMessage",
    } < set(schemas)
    messages = [r for r in records if isinstance(r, Message)]
    assert len(messages) >= 2 * 50, f"{len(messages)} messages of {2 * i} read back from the flushed chunks"
    # `replay`'s loader reads the file without its summary up to where it breaks off.
    assert SessionRecording.load(path).trajectory.frames >= 0.75 * i


@pytest.mark.parametrize("where", ["under a file", "read-only"])
def test_a_recording_that_cannot_be_written_stops_for_its_session_and_says_so(tmp_path, where):
    """A record folder that cannot be made (under a file), or one that exists and takes no file
    whoever writes (sysfs refuses even root, who ignores a folder's permissions): the session is
    told, nothing raises."""
    from inhand_tracker.service.server.recording import SessionRecorder

    traj = Trajectory.load(TRAJECTORY)
    info, request = _session(traj)
    said = {}
    if where == "under a file":
        blocked = tmp_path / "a_file"
        blocked.write_text("")
        folder = blocked / "recordings"
    else:
        folder = Path("/sys")
        if not folder.is_dir() or (os.access(folder, os.W_OK) and _writable(folder)):
            pytest.skip("no folder here refuses every write")
    recorder = SessionRecorder(folder, "default", said=lambda s, m: said.setdefault(s, m))
    recorder.open(info, request)
    recorder.frame(traj.frame(0, info.session))
    recorder.drop(info.session)
    assert said[info.session].startswith("recording: stopped for this session: ") and str(folder) in said[info.session]


def _writable(folder: Path) -> bool:
    try:
        (folder / ".inhand-probe").touch()
    except OSError:
        return False
    (folder / ".inhand-probe").unlink()
    return True


def _stream(svc: ServiceProcess, traj: Trajectory, seconds: float, then=None) -> tuple[TrackerClient, int]:
    """A robot streaming ``traj`` to ``svc`` at 30 Hz for ``seconds``, ``then()`` called once the
    first estimate came (every kernel compiled); returns its client (open) and the last seq the
    service answered."""
    import time

    client = TrackerClient(connect=[svc.endpoint])
    svc.wait_ready(client)
    client.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4)
    client.send(traj.frame(0, client.info.session, seq=0))
    client.latest_pose(timeout=120, after_seq=-1)
    if then is not None:
        then()
    began, i, last = time.monotonic(), 1, 0
    while time.monotonic() - began < seconds:
        client.send(traj.frame(i % traj.frames, client.info.session, seq=i))
        with contextlib.suppress(TimeoutError):
            last = client.latest_pose(timeout=0.1, after_seq=last).seq
        i += 1
        time.sleep(1 / 30)
    return client, last


def test_a_service_killed_with_sigkill_leaves_a_readable_recording(tmp_path):
    """kill -9 of a real `serve --record`: the chunks flushed each second read back, so at most
    the last second is lost."""
    from mcap.data_stream import EndOfFile
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    from inhand_tracker.protocol.ros2_records import decode_record

    traj = Trajectory.load(TRAJECTORY)
    svc = ServiceProcess(free_port(), record=str(tmp_path))
    client, last = _stream(svc, traj, 4.0)
    svc.proc.kill()
    svc.proc.wait(timeout=10)
    client.close()
    (path,) = tmp_path.glob("*/*.mcap")
    records = []
    with contextlib.suppress(EndOfFile):  # the file ends where the process stopped
        records.extend(StreamReader(path.open("rb"), skip_magic=False).records)
    channel = next(r.id for r in records if isinstance(r, Channel) and r.topic == CHANNELS["estimate"])
    estimates = [
        decode_record("estimate", r.data)["seq"] for r in records if isinstance(r, Message) and r.channel_id == channel
    ]
    assert last > 60, f"the service answered up to seq {last}"
    # The chunks are flushed four times a second: at most the last quarter second is lost.
    assert max(estimates) >= last - 15, f"estimates read back up to seq {max(estimates)}; answered up to {last}"
    read = SessionRecording.load(path)  # what `replay` opens
    assert read.trajectory.frames >= 0.9 * (last + 1), (read.trajectory.frames, last)


def test_a_full_disk_stops_the_recording_and_the_session_tracks_on(tmp_path):
    """Writes past 64 KiB fail in the service's process once it tracks (the kernel's file-size
    limit: EFBIG, as a full disk's ENOSPC): the recording stops for the session and its status
    says so; the session keeps tracking."""
    traj = Trajectory.load(TRAJECTORY)
    svc = ServiceProcess(free_port(), record=str(tmp_path))
    client, last = _stream(svc, traj, 4.0, then=lambda: svc.limit_files(64 * 1024))
    try:
        status = client.status()
        assert status.last_error is not None and status.last_error.startswith("recording: stopped"), status
        assert last > 60 and status.frames > 60, (last, status.frames)  # tracking went on
        (path,) = tmp_path.glob("*/*.mcap")
        assert SessionRecording.load(path).trajectory.frames > 0  # cut mid-record, it still opens
    finally:
        client.close()
        svc.stop()


def test_a_read_only_record_folder_is_refused_before_the_service_starts():
    """A record folder that takes no file whoever writes (sysfs refuses even root) is said in one
    line, exit 4, before anything loads: a recording asked for is not silently lost. A folder
    that fails later (a full disk) stops the recording and the sessions track on (above)."""
    if not Path("/sys").is_dir() or _writable(Path("/sys")):
        pytest.skip("no folder here refuses every write")
    out = subprocess.run(
        [sys.executable, "-m", "inhand_tracker.service.cli", "serve", "--listen", f"tcp/127.0.0.1:{free_port()}",
         "--record", "/sys", "--device", "cpu"], capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 4 and lines == ["serve --record: cannot write to '/sys': Permission denied"], out.stderr
