"""A ROS 2 robot tracked with none of this project's client code: an independent rmw_zenoh client
(zenoh-ros2-sdk, from PyPI, with the .msg files a ROS 2 install holds) publishes the robot's joint
states, commands and fingertip wrenches on its own topics; the session the service's config declares
reads them, and the pose comes back on a ROS 2 topic. Everything meets at a Zenoh router, the service
connected to it as a Zenoh client, as rmw_zenoh's own router requires (it relays nothing between
plain peers)."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from service_process import ROOT, ServiceProcess, free_port

from inhand_tracker.client import TrackerClient, zenoh_config
from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.paths import CONFIG_DIR, DATA_DIR

TRAJECTORY = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
MSGS = Path(__file__).parent / "data" / "ros2_msgs"
DOMAIN = 5
HEADER, TIME, VECTOR = "std_msgs/msg/Header", "builtin_interfaces/msg/Time", "geometry_msgs/msg/Vector3"
FRAMES = 40


def _joint_names(robot: str) -> tuple[str, ...]:
    from inhand_tracker.sim_backend import load_robot
    from inhand_tracker.sim_backend.kinematics import Kinematics

    return Kinematics(load_robot(CONFIG_DIR / "robots" / f"{robot}.toml")).layout.joint_names


@pytest.fixture
def sdk_session():
    """zenoh-ros2-sdk keeps one Zenoh session per process, connected where its first user said: the
    test's own, made fresh before it and closed after it, so no other test inherits one to a
    service that is gone."""
    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    def fresh() -> None:
        if ZenohSession._instance is not None:
            ZenohSession._instance.close()
        message_registry._registry = None  # it holds the session it was made with

    fresh()
    yield
    fresh()


def test_a_ros_native_robot_is_tracked_from_its_topics_and_its_pose_read_back_on_ros(sdk_session):
    from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber
    from zenoh_ros2_sdk.discovery import get_topic_info
    from zenoh_ros2_sdk.message_registry import get_registry

    traj = Trajectory.load(TRAJECTORY)
    names = _joint_names(traj.robot)
    sensors = traj.frame(0, "").force.shape[0]
    declared = {
        "name": "ros_hand", "robot": traj.robot, "object": traj.object, "p0": traj.truth.initial_pose.tolist(),
        "worlds": 4, "joint_states": "/hand/joint_states", "commands": "/hand/joint_commands",
        "wrenches": [f"/hand/tip{i}/wrench" for i in range(sensors)],
    }  # fmt: skip
    port = free_port()
    router = f"tcp/127.0.0.1:{port}"
    conf = zenoh_config(listen=[router])
    conf.insert_json5("mode", '"router"')
    stack = contextlib.ExitStack()
    stack.enter_context(zenoh.open(conf))
    svc = ServiceProcess(
        free_port(), listen=False, connect=router, zenoh_mode="client", ros2="true",
        ros2_domain_id=str(DOMAIN), ros2_sessions=json.dumps([declared]), idle_timeout_s="4",
    )  # fmt: skip
    get_registry(str(MSGS))  # the .msg files a ROS 2 install would hold; nothing fetched
    on = {"router_ip": "127.0.0.1", "router_port": port, "domain_id": DOMAIN, "node_name": "hand_driver"}
    poses, lock = [], threading.Lock()
    try:
        with TrackerClient(connect=[router], zenoh_mode="client") as probe:
            svc.wait_ready(probe)
        joints = ROS2Publisher("/hand/joint_states", "sensor_msgs/msg/JointState", **on)
        commands = ROS2Publisher("/hand/joint_commands", "sensor_msgs/msg/JointState", **on)
        wrenches = [ROS2Publisher(t, "geometry_msgs/msg/WrenchStamped", **on) for t in declared["wrenches"]]
        ros = joints.session_mgr.store.types  # the classes of the .msg files, as the SDK built them
        Header, Time, Wrench, Vector3 = (ros[t] for t in (HEADER, TIME, "geometry_msgs/msg/Wrench", VECTOR))
        nothing = np.zeros(0)
        pose_topic = "/inhand/ros_hand/pose"

        def on_pose(msg) -> None:
            with lock:
                poses.append(msg)

        sub = ROS2Subscriber(pose_topic, "geometry_msgs/msg/PoseWithCovarianceStamped", on_pose, **on)
        time.sleep(1.0)  # the subscriptions reach each other
        order = np.arange(len(names))[::-1]  # the driver names its joints in an order of its own

        def send(i: int, stamp: float) -> None:
            f = traj.frame(i, "")
            header = Header(stamp=Time(sec=int(stamp), nanosec=round((stamp - int(stamp)) * 1e9)), frame_id="")
            for k, pub in enumerate(wrenches):
                force = Vector3(x=float(f.force[k, 0]), y=float(f.force[k, 1]), z=float(f.force[k, 2]))
                pub.publish(header=header, wrench=Wrench(force=force, torque=Vector3(x=0.0, y=0.0, z=0.0)))
            named = {"header": header, "name": [names[j] for j in order], "velocity": nothing, "effort": nothing}
            commands.publish(position=f.controls.astype(np.float64)[order], **named)
            time.sleep(0.02)  # the wrenches and the command before the joint state that makes the frame
            joints.publish(position=f.q.astype(np.float64)[order], **named)

        def wait_for(count: int, timeout: float) -> None:
            deadline = time.monotonic() + timeout
            while len(poses) < count and time.monotonic() < deadline:
                time.sleep(0.01)
            assert len(poses) >= count, f"{len(poses)} of {count} poses on {pose_topic}: {svc.proc.poll()}"

        t0 = 1000.0  # the robot's clock: a stamp of 0 would read as "unset"
        for i in range(FRAMES):
            send(i, t0 + traj.stamp[i])
            wait_for(i + 1, 600 if i == 0 else 60)  # the first builds the session's population
        stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in poses]
        np.testing.assert_allclose(stamps, t0 + traj.stamp[:FRAMES], atol=1e-6)
        tracked = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] for m in poses])
        error = np.linalg.norm(tracked - traj.truth.pose[:FRAMES, :3], axis=1)
        assert error.mean() < 0.015, f"mean position error {error.mean() * 1e3:.1f} mm over {FRAMES} frames"

        # `ros2 topic info` sees the service subscribed to the robot's topic, and publishing its pose.
        about = get_topic_info("/hand/joint_states", DOMAIN, "127.0.0.1", port, timeout=2.0, verbose=True)
        assert "inhand_tracker" in [s.node_name for s in about.subscribers]
        assert get_topic_info(pose_topic, DOMAIN, "127.0.0.1", port, 2.0).publisher_count == 1

        # The robot falls silent past the idle timeout: the session closes; its next joint state opens it again.
        with TrackerClient(connect=[router], zenoh_mode="client") as probe:
            deadline = time.monotonic() + 30
            while probe.service_info(timeout=2.0).sessions and time.monotonic() < deadline:
                time.sleep(0.2)
            assert probe.service_info(timeout=2.0).sessions == 0
            send(0, t0 + 100.0)
            wait_for(FRAMES + 1, 120)
            assert probe.service_info(timeout=2.0).sessions == 1
        for pub in [joints, commands, *wrenches]:
            pub.close()
        sub.close()
    finally:
        svc.stop()
        stack.close()
    log = svc.proc.stdout.read()
    assert log.count("ROS 2 session 'ros_hand' opened") == 2, log[-3000:]
    assert "Traceback" not in log, log[-3000:]


@pytest.mark.parametrize(
    ("declared", "said"),
    [
        ({"robot": "no_such_hand"}, "ros2_sessions[0].robot: 'no_such_hand' is not one of"),
        ({"joint_states": "joint states"}, "ros2_sessions.0.joint_states"),
    ],
)
def test_a_declared_session_the_service_cannot_serve_is_refused_at_start_in_one_line(declared, said):
    session = {"name": "left", "robot": "allegro", "object": "foam_brick", "p0": [0, 0, 0.1, 0, 0, 0, 1]} | declared
    env = {"INHAND_ROS2_SESSIONS": json.dumps([session]), "INHAND_LISTEN": f"tcp/127.0.0.1:{free_port()}"}
    run = subprocess.run(
        [sys.executable, "-m", "inhand_tracker.service.cli", "serve", "--device", "cpu"],
        cwd=ROOT, env={**os.environ, **env}, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 2, run.stdout + run.stderr
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert said in run.stderr and len(lines) == 1, run.stderr


def test_two_services_on_one_router_publish_as_nodes_and_topics_of_their_own():
    """One service per GPU behind one router, each with a session of the default name: each service's
    node and topics live in its own namespace (its name), so neither's pose reaches the other's topic."""

    traj = Trajectory.load(TRAJECTORY)
    port = free_port()
    router = f"tcp/127.0.0.1:{port}"
    conf = zenoh_config(listen=[router])
    conf.insert_json5("mode", '"router"')
    services = []
    with zenoh.open(conf) as z, contextlib.ExitStack() as stack:
        try:
            for name in ("gpu-a", "gpu-b"):
                settings = {"name": name, "connect": router, "ros2": "true", "ros2_domain_id": "6"}
                settings["idle_timeout_s"] = "120"  # both sessions stay open while the other service warms
                services.append(ServiceProcess(free_port(), listen=False, **settings))
            robots = [stack.enter_context(TrackerClient(connect=[router], service=n)) for n in ("gpu-a", "gpu-b")]
            for svc, robot in zip(services, robots, strict=True):
                svc.wait_ready(robot)
            for robot in robots:
                info = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=2)
                assert info.name == "allegro_foam_brick"
                robot.send(traj.frame(0, info.session))
                robot.latest_pose(timeout=60, after_seq=0)
            # The publishers' liveliness tokens, in rmw_zenoh's layout (which `ros2 topic list` and
            # `ros2 topic info -v` read): one node per service, inhand_tracker in its service's namespace.
            mine = ["/gpu_a/inhand/allegro_foam_brick/pose", "/gpu_b/inhand/allegro_foam_brick/pose"]
            tokens = [str(r.ok.key_expr).split("/") for r in z.liveliness().get("@ros2_lv/6/**", timeout=2) if r.ok]
            publishers = sorted((t[9], t[7], t[8]) for t in tokens if t[5] == "MP" and t[9].endswith("%pose"))
            assert publishers == [(t.replace("/", "%"), t[:6].replace("/", "%"), "inhand_tracker") for t in mine]
        finally:
            stack.close()
            for svc in services:
                svc.stop()
