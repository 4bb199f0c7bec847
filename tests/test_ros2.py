"""ROS 2 sees the service's estimates without a bridge, checked against independent
implementations: zenoh-ros2-sdk (a third-party rmw_zenoh client from PyPI) subscribes as a ROS 2
node would and lists the topics as `ros2 topic list` does; rosbags decodes the CDR."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from service_process import ServiceProcess, free_port

from inhand_tracker.client import TrackerClient
from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.paths import DATA_DIR

TRAJECTORY = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
MSGS = Path(__file__).parent / "data" / "ros2_msgs"
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"


@pytest.fixture(scope="module")
def service():
    port = free_port()
    domain, os.environ["ROS_DOMAIN_ID"] = os.environ.get("ROS_DOMAIN_ID"), "3"  # as a ROS 2 shell sets it
    try:
        svc = ServiceProcess(port, ros2="true", ros2_tf="true", ros2_frame_id="allegro_world")
    finally:
        if domain is None:
            del os.environ["ROS_DOMAIN_ID"]
        else:
            os.environ["ROS_DOMAIN_ID"] = domain
    with TrackerClient(connect=[svc.endpoint]) as probe:
        svc.wait_ready(probe)
    yield svc, port
    svc.stop()


def test_a_third_party_rmw_zenoh_node_receives_the_pose_and_sees_the_topics(service):
    from zenoh_ros2_sdk import ROS2Subscriber
    from zenoh_ros2_sdk.attachment import Attachment
    from zenoh_ros2_sdk.discovery import get_topic_info, get_topic_names_and_types
    from zenoh_ros2_sdk.message_registry import get_registry

    svc, port = service
    get_registry(str(MSGS))  # the .msg files a ROS 2 install would hold; nothing fetched
    traj = Trajectory.load(TRAJECTORY)
    with TrackerClient(connect=[svc.endpoint]) as robot:
        info = robot.open_session(
            traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4, name="left_hand"
        )
        topic = "/inhand/left_hand/pose"  # named by the robot, so a launch file can name it too
        received, attachments, lock = [], [], threading.Lock()

        def on_pose(msg) -> None:
            with lock:
                received.append(msg)

        sub = ROS2Subscriber(topic, POSE, on_pose, router_ip="127.0.0.1", router_port=port, domain_id=3)
        raw = sub.session_mgr.session.declare_subscriber(
            "3/**", lambda s: attachments.append(bytes(s.attachment.to_bytes())) if s.attachment else None
        )
        time.sleep(1.0)  # the subscriptions reach the service
        estimates = []
        for i in range(5):
            robot.send(traj.frame(i, info.session))
            estimates.append(robot.latest_pose(timeout=60, after_seq=i))
        deadline = time.monotonic() + 10
        # The raw subscriber sees the pose and /tf samples on its own schedule: wait for both.
        while (len(received) < 5 or len(attachments) < 10) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(received) == 5, f"the rmw_zenoh subscriber got {len(received)} of 5 poses"
        for msg, est in zip(received, estimates, strict=True):
            assert msg.header.frame_id == "allegro_world"
            assert msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 == pytest.approx(est.stamp, abs=1e-6)
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            np.testing.assert_allclose([p.x, p.y, p.z, q.x, q.y, q.z, q.w], est.pose, rtol=0, atol=1e-7)
            np.testing.assert_allclose(msg.pose.covariance.reshape(6, 6), est.covariance, rtol=1e-6, atol=1e-12)

        # rmw_zenoh's attachment on every sample: the publisher's sequence, a source time, its GID.
        poses = [Attachment.from_bytes(a) for a in attachments]
        assert len(poses) >= 5
        by_gid: dict[bytes, list[int]] = {}
        for a in poses:
            assert len(a.gid) == 16 and abs(a.timestamp_ns - time.time_ns()) < 60e9
            by_gid.setdefault(a.gid, []).append(a.sequence_id)
        assert sorted(len(s) for s in by_gid.values()) == [5, 5]  # the pose and /tf publishers
        assert all(s == list(range(1, 6)) for s in by_gid.values())

        # `ros2 topic list` and `ros2 topic info` read the liveliness tokens.
        topics = dict(get_topic_names_and_types(domain_id=3, router_ip="127.0.0.1", router_port=port, timeout=2.0))
        assert topics[topic] == [POSE] and topics["/tf"] == ["tf2_msgs/msg/TFMessage"]
        about = get_topic_info(topic, 3, "127.0.0.1", port, timeout=2.0, verbose=True)
        assert (about.publisher_count, about.subscriber_count, about.publishers[0].node_name) == (
            1,
            1,
            "inhand_tracker",
        )
        assert about.publishers[0].type_hash == sub.type_hash  # the SDK's own hash of the .msg files

        robot.close_session()  # its publisher goes (the SDK's own subscription stays listed)
        deadline = time.monotonic() + 10
        while get_topic_info(topic, 3, "127.0.0.1", port, 1.0).publisher_count and time.monotonic() < deadline:
            time.sleep(0.2)
        assert get_topic_info(topic, 3, "127.0.0.1", port, 1.0).publisher_count == 0, (
            "the publisher outlived its session"
        )
        raw.undeclare()
        sub.close()


def test_the_cdr_is_what_rosbags_decodes_and_the_keys_are_rmw_zenohs():
    """The message and key layout, without a service: a pose through the service's publisher on a
    session of our own, decoded by rosbags' ROS 2 type store."""
    from rosbags.typesys import Stores, get_typestore

    from inhand_tracker.protocol import Estimate, SessionInfo
    from inhand_tracker.service.server.ros2 import RosTopics

    store = get_typestore(Stores.ROS2_HUMBLE)
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    port = free_port()
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    with zenoh.open(conf) as z:
        got: list[zenoh.Sample] = []
        z.declare_subscriber("**", got.append)
        tokens = [str(r.ok.key_expr) for r in z.liveliness().get("@ros2_lv/**", timeout=1) if r.ok]
        assert tokens == []
        ros = RosTopics(z, domain_id=7, frame_id="base", tf=True)
        ros.open(
            SessionInfo(
                session="0a1b2c",
                token="t",
                robot="allegro",
                object="foam_brick",
                joint_names=[],
                sensor_names=[],
                worlds=1,
                method="PBO",
                name="lab2/bench_left",  # a name in a namespace: a topic and a frame below it
            )
        )
        est = Estimate(
            session="0a1b2c", seq=3, stamp=12.25, pose=np.array([0.1, -0.2, 0.3, 0, 0, 0.6, 0.8]),
            mean_pose=np.array([0, 0, 0, 0, 0, 0, 1.0]), covariance=np.diag(np.arange(1, 7) * 1e-6),
            cost=0.5, mass=0.1, friction=0.8, status="tracking", latency_ms=1.0,
        )  # fmt: skip
        ros.estimate(est)
        deadline = time.monotonic() + 5
        while len(got) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        tokens = sorted(str(r.ok.key_expr) for r in z.liveliness().get("@ros2_lv/**", timeout=1) if r.ok)
        ros.close()
    digest = store.hash_rihs01(POSE)
    dds = "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
    (sample,) = [s for s in got if str(s.key_expr).startswith("7/inhand/")]
    assert str(sample.key_expr) == f"7/inhand/lab2/bench_left/pose/{dds}/{digest}"
    (tf,) = [s for s in got if str(s.key_expr).startswith("7/tf/")]
    (child,) = store.deserialize_cdr(bytes(tf.payload.to_bytes()), "tf2_msgs/msg/TFMessage").transforms
    assert (child.header.frame_id, child.child_frame_id) == ("base", "lab2/bench_left")
    msg = store.deserialize_cdr(bytes(sample.payload.to_bytes()), POSE)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (12, 250_000_000, "base")
    assert msg.pose.pose.orientation.z == pytest.approx(0.6) and msg.pose.covariance[35] == pytest.approx(6e-6)
    zid = tokens[0].split("/")[2]
    assert tokens == sorted(
        [
            f"@ros2_lv/7/{zid}/0/0/NN/%/%/inhand_tracker",
            # /tf keeps 100 as tf2's broadcasters declare; a pose keeps ROS's default 10.
            f"@ros2_lv/7/{zid}/0/1/MP/%/%/inhand_tracker/%tf/tf2_msgs::msg::dds_::TFMessage_/"
            f"{store.hash_rihs01('tf2_msgs/msg/TFMessage')}/::,100:,:,:,,",
            f"@ros2_lv/7/{zid}/0/2/MP/%/%/inhand_tracker/%inhand%lab2%bench_left%pose/{dds}/{digest}/::,10:,:,:,,",
        ]
    )
