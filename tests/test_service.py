"""The service over real Zenoh sessions on 127.0.0.1 (scouting off, free ports), with the service
in its own process (`inhand-tracker serve`): estimates equal to the in-process session manager,
bad input refused with the field and the numbers while the service goes on, a killed robot's
session closed within the timeout, a restarted service reopened, several sessions at once."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from service_process import ServiceProcess, free_port

from inhand_tracker.client import TrackerClient, TrackerError
from inhand_tracker.protocol import (
    PROTOCOL_VERSION,
    CloseSession,
    Error,
    ErrorCode,
    Keys,
    OpenSession,
    Trajectory,
    decode,
    encode,
)
from inhand_tracker.service.paths import DATA_DIR

TRAJECTORY = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def service():
    svc = ServiceProcess(free_port())
    with TrackerClient(connect=[svc.endpoint]) as probe:
        svc.wait_ready(probe)
    yield svc
    took = svc.stop()
    assert svc.proc.returncode == 0 and took < 10, (svc.proc.returncode, took)


def _open(client: TrackerClient, traj: Trajectory, **kw):
    return client.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, **kw)


def test_client_imports_no_torch_warp_or_newton():
    code = (
        "import sys, inhand_tracker.client; bad = {'torch', 'warp', 'newton'} & set(sys.modules); assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_tracks_with_the_same_estimates_as_the_in_process_manager(service):
    from inhand_tracker.protocol import OpenSession as Open
    from inhand_tracker.service.server.config import ServiceConfig
    from inhand_tracker.service.server.sessions import SessionManager
    from inhand_tracker.sim_backend import load_catalog, load_robot

    traj, frames = Trajectory.load(TRAJECTORY), 40
    with TrackerClient(connect=[service.endpoint]) as client:
        info = _open(client, traj)
        assert info.worlds == 40 and info.joint_names[0] == "wrist_x" and len(info.sensor_names) == 4
        remote = []
        for i in range(frames):
            client.send(traj.frame(i, info.session))
            remote.append(client.latest_pose(timeout=30, after_seq=i))
        status = client.status()
        assert (status.frames, status.gaps, status.errors) == (frames, 0, 0) and status.latency_p99_ms > 0
        client.close_session()

    robot = load_robot(ROOT / "configs/robots/allegro.toml")
    manager = SessionManager(ServiceConfig(groups=1, device="cpu", rate_hz=0), {robot.name: robot}, load_catalog())
    local_info = manager.open(Open(robot=traj.robot, object=traj.object, p0=traj.truth.initial_pose,
                                   q0=traj.truth.initial_q))  # fmt: skip
    pool = manager.sessions[local_info.session].pool
    for i in range(frames):
        manager.submit(traj.frame(i, local_info.session, token=local_info.token))
        (local,) = manager.step(pool)
        assert local.seq == remote[i].seq == i
        assert np.array_equal(local.pose, remote[i].pose), f"frame {i}: {local.pose} != {remote[i].pose}"
        assert np.array_equal(local.covariance, remote[i].covariance)


def test_bad_input_is_refused_with_the_field_and_the_service_goes_on(service):
    traj = Trajectory.load(TRAJECTORY)
    keys = Keys("default")
    with TrackerClient(connect=[service.endpoint]) as client:
        z = client._zenoh

        def rpc(key: str, payload: bytes) -> Error:
            (reply,) = list(z.get(key, payload=payload, timeout=30))
            assert reply.err is not None
            return decode(bytes(reply.err.payload.to_bytes()), Error)

        err = rpc(keys.open, b"\xc1not msgpack")
        assert err.code == ErrorCode.BAD_REQUEST and "not valid msgpack" in err.message
        good = OpenSession(robot=traj.robot, object=traj.object, p0=traj.truth.initial_pose)
        err = rpc(keys.open, encode(good.model_copy(update={"protocol": 99})))
        assert err.code == ErrorCode.VERSION_MISMATCH and "v99" in err.message and f"v{PROTOCOL_VERSION}" in err.message
        with pytest.raises(TrackerError) as exc:
            client.open_session("shadow_hand", traj.object, traj.truth.initial_pose)
        assert exc.value.code == ErrorCode.UNKNOWN_ROBOT and "'shadow_hand'" in exc.value.message
        with pytest.raises(TrackerError) as exc:
            client.open_session(traj.robot, "teapot", traj.truth.initial_pose)
        assert exc.value.code == ErrorCode.UNKNOWN_OBJECT and "allegro" not in exc.value.message
        raw = msgpack.unpackb(encode(good), raw=False)
        raw["p0"]["data"] = np.array([0, 0, np.nan, 0, 0, 0, 1], np.float32).tobytes()
        err = rpc(keys.open, msgpack.packb(raw, use_bin_type=True))
        assert err.code == ErrorCode.BAD_REQUEST and "OpenSession.p0" in err.message and "nan" in err.message
        err = rpc(keys.open, b"\x80" + b"x" * (2 << 20))
        assert err.code == ErrorCode.BAD_REQUEST and "exceeds the limit" in err.message
        (reply,) = list(z.get(keys.pose("nosuchsession"), timeout=10))
        err = decode(bytes(reply.err.payload.to_bytes()), Error)
        assert err.code == ErrorCode.BAD_REQUEST and "'nosuchsession': is not open" in err.message
        ask = encode(CloseSession(session="nosuchsession", token="0" * 32))
        (reply,) = list(z.get(keys.status("nosuchsession"), payload=ask, timeout=10))
        assert decode(bytes(reply.err.payload.to_bytes()), Error).code == ErrorCode.FORBIDDEN

        info = _open(client, traj)
        client.send(traj.frame(0, info.session))
        client.latest_pose(timeout=30, after_seq=0)
        short = traj.frame(1, info.session, token=info.token).model_copy(update={"q": traj.q[1][:21]})
        raw = msgpack.unpackb(encode(traj.frame(1, info.session, token=info.token)), raw=False)
        raw["force"]["data"] = np.full(12, np.inf, np.float32).tobytes()
        bad_frames = [
            (encode(short), "RobotFrame.q: expected shape (22,), got (21,) (seq 1)"),  # wrong size
            (msgpack.packb(raw, use_bin_type=True), "RobotFrame.force: 12 non-finite values"),
            (b"\x93garbage", "payload: not valid msgpack"),
        ]
        for n, (payload, message) in enumerate(bad_frames, start=1):
            z.put(keys.frame(info.session), payload)
            deadline = time.monotonic() + 10
            while (status := client.status()).errors < n and time.monotonic() < deadline:
                time.sleep(0.05)
            assert status.errors == n and message in status.last_error, status.last_error
        client.send(traj.frame(0, info.session))  # a duplicate: dropped and counted
        deadline = time.monotonic() + 10
        while client.status().duplicates < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert client.status().duplicates == 1
        client.send(traj.frame(1, info.session))  # and the session goes on
        assert client.latest_pose(timeout=30, after_seq=1).seq == 1
        assert client.service_info().sessions == 1
        client.close_session()


@pytest.mark.slow
def test_a_killed_robot_s_session_is_closed_and_a_restarted_service_reopened():
    svc = ServiceProcess(free_port(), groups=2, timeout_s=1.0)
    robot = textwrap.dedent(f"""
        import numpy as np, time
        from inhand_tracker.client import TrackerClient
        from inhand_tracker.protocol import Trajectory
        traj = Trajectory.load({str(TRAJECTORY)!r})
        c = TrackerClient(connect=[{svc.endpoint!r}])
        info = c.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q)
        c.send(traj.frame(0, info.session))
        c.latest_pose(timeout=60, after_seq=0)
        print("ready", flush=True)
        time.sleep(600)
    """)
    try:
        with TrackerClient(connect=[svc.endpoint]) as watcher:
            svc.wait_ready(watcher)
            proc = subprocess.Popen([sys.executable, "-c", robot], cwd=ROOT, stdout=subprocess.PIPE, text=True)
            assert proc.stdout.readline().strip() == "ready"
            assert watcher.service_info().sessions == 1
            proc.kill()
            proc.wait()
            t0 = time.monotonic()
            while watcher.service_info().sessions and time.monotonic() - t0 < 10:
                time.sleep(0.1)
            assert watcher.service_info().sessions == 0, "the dead robot's session is still open"
            assert time.monotonic() - t0 < 1.0 + 3.0

            traj = Trajectory.load(TRAJECTORY)
            info = _open(watcher, traj)
            watcher.send(traj.frame(0, info.session))
            watcher.latest_pose(timeout=60, after_seq=0)
            assert svc.stop() < 5.0  # SIGTERM closes everything promptly
            port = int(svc.endpoint.rsplit(":", 1)[1])
            svc = ServiceProcess(port, groups=2)
            svc.wait_ready(watcher)
            with pytest.raises(TrackerError) as exc:
                watcher.status()
            assert exc.value.code == ErrorCode.FORBIDDEN
            with pytest.raises(TrackerError):  # the old session died with the old service
                watcher.close_session()
            info = _open(watcher, traj)
            watcher.send(traj.frame(0, info.session))
            assert watcher.latest_pose(timeout=60, after_seq=0).seq == 0
    finally:
        if svc.proc.poll() is None:
            svc.stop()


@pytest.mark.slow
def test_eight_sessions_at_once_all_get_their_estimates():
    svc = ServiceProcess(free_port(), groups=8)
    traj = Trajectory.load(TRAJECTORY)
    clients = []
    try:
        clients = [TrackerClient(connect=[svc.endpoint]) for _ in range(8)]
        svc.wait_ready(clients[0])
        infos = [_open(c, traj, worlds=8) for c in clients]
        assert len({i.session for i in infos}) == 8
        for f in range(5):
            for c, info in zip(clients, infos, strict=True):
                c.send(traj.frame(f, info.session))
            for c in clients:
                assert c.latest_pose(timeout=60, after_seq=f).seq == f
        assert clients[0].service_info().sessions == 8
    finally:
        for c in clients:
            c.close()
        svc.stop()


def test_a_wildcard_pose_query_answers_once_per_open_session(service):
    traj = Trajectory.load(TRAJECTORY)
    with (
        TrackerClient(connect=[service.endpoint]) as a,
        TrackerClient(connect=[service.endpoint]) as b,
        TrackerClient(connect=[service.endpoint]) as watcher,
    ):
        sessions = {}
        for robot in (a, b):
            info = _open(robot, traj, worlds=4)
            robot.send(traj.frame(0, info.session))
            sessions[info.session] = robot.latest_pose(timeout=60, after_seq=0)
        seen = watcher.poses()
        assert seen.keys() == sessions.keys()
        for session, estimate in sessions.items():
            np.testing.assert_array_equal(seen[session].pose, estimate.pose)
        for selector in (Keys("default").every("pose"), "inhand/**/pose"):
            replies = list(watcher._zenoh.get(selector, timeout=10))
            keys = sorted(str(r.ok.key_expr) for r in replies)
            assert keys == sorted(Keys("default").pose(s) for s in sessions), (selector, keys)
            # Every sample names its message: msgpack, with the schema inhand.v7.Estimate.
            assert {str(r.ok.encoding) for r in replies} == {f"application/msgpack;inhand.v{PROTOCOL_VERSION}.Estimate"}
        a.close_session()
        assert watcher.poses().keys() == {b.info.session}
        b.close_session()


def test_examples_run_as_processes(service):
    watcher = subprocess.Popen(
        [sys.executable, "examples/pose_watcher.py", "--connect", service.endpoint, "--count", "5"],
        cwd=ROOT, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert watcher.stdout.readline().startswith("latest: ")
    assert watcher.stdout.readline().strip() == "watching"
    cli = subprocess.Popen(
        [sys.executable, "-m", "inhand_tracker.service.cli", "watch", "--connect", service.endpoint, "--count", "3"],
        cwd=ROOT, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert cli.stdout.readline().strip() == "watching service 'default'"
    robot = subprocess.run(
        [sys.executable, "examples/robot_replay.py", str(TRAJECTORY), "--connect", service.endpoint, "--frames", "12",
         "--camera-hz", "10"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert robot.returncode == 0, robot.stderr[-2000:]
    assert "frame 11: " in robot.stdout and "position error" in robot.stdout, robot.stdout
    assert "done: 12 frames, 4 camera poses" in robot.stdout, robot.stdout
    out, _ = watcher.communicate(timeout=60)
    assert watcher.returncode == 0 and len([line for line in out.splitlines() if " seq " in line]) == 5
    out, _ = cli.communicate(timeout=60)
    assert cli.returncode == 0 and len([line for line in out.splitlines() if " seq " in line]) == 3


def test_touch_presence_is_per_session_in_a_shared_population():
    """A robot without touch sensing, sharing a population with one that has it, is scored by
    joints and sensor poses alone: its contact terms stay zero while the other's count."""
    from inhand_tracker.protocol import OpenSession as Open
    from inhand_tracker.service.server import ServiceConfig, SessionManager
    from inhand_tracker.sim_backend import load_catalog, load_robot

    traj = Trajectory.load(TRAJECTORY)
    robot = load_robot(ROOT / "configs/robots/allegro.toml")
    manager = SessionManager(ServiceConfig(groups=2, device="cpu", rate_hz=0), {robot.name: robot}, load_catalog())
    open_one = lambda: manager.open(Open(robot=traj.robot, object=traj.object, p0=traj.truth.initial_pose,  # noqa: E731
                                         q0=traj.truth.initial_q))  # fmt: skip
    touch_info, blind_info = open_one(), open_one()
    touch, blind = touch_info.session, blind_info.session
    pool = manager.sessions[touch].pool
    assert manager.sessions[blind].pool is pool
    g_touch, g_blind = manager.sessions[touch].group, manager.sessions[blind].group
    contact_terms = slice(3, 6)  # contact disagreement, force magnitude and direction
    felt = 0.0
    for i in range(60):  # the fingers close on the brick from frame 41
        manager.submit(traj.frame(i, touch, token=touch_info.token))
        no_touch = {"force": None, "slip": None, "slip_dir": None, "spin": None, "spin_sense": None}
        manager.submit(traj.frame(i, blind, token=blind_info.token).model_copy(update=no_touch))
        manager.step(pool)
        terms = pool.tracker.cost.last_terms
        assert float(terms[g_blind, :, contact_terms].abs().sum()) == 0.0, f"frame {i}"
        felt += float(terms[g_touch, :, contact_terms].abs().sum())
    assert felt > 0


def test_a_failing_step_fails_its_sessions_and_the_service_goes_on(caplog):
    """An exception in the GPU loop is logged with its traceback, the sessions of that population
    say why in their status, and the loop goes on serving the others."""
    import logging

    from inhand_tracker.service.server import ServiceConfig, TrackerNode

    traj = Trajectory.load(TRAJECTORY)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = ServiceConfig(listen=(endpoint,), device="cpu", groups=1, rate_hz=0)
    with caplog.at_level(logging.ERROR), TrackerNode(config) as node, TrackerClient(connect=[endpoint]) as client:
        broken = _open(client, traj)
        step = node.manager.step

        def fault(pool):  # a fault injected into one population's step
            if broken.session in [s.id for s in pool.active]:
                raise RuntimeError("device lost")
            return step(pool)

        node.manager.step = fault
        client.send(traj.frame(0, broken.session))
        deadline = time.monotonic() + 30
        while (status := client.status(timeout=10)).last_error is None:
            assert time.monotonic() < deadline
            time.sleep(0.1)
        assert "RuntimeError: device lost" in status.last_error and status.errors == 1  # its frame
        assert any("device lost" in r.getMessage() or (r.exc_info and "device lost" in str(r.exc_info[1]))
                   for r in caplog.records)  # fmt: skip
        assert not node.failed.is_set()
        node.keys.session_of = lambda key: 1 / 0  # a fault in a Zenoh handler itself
        (reply,) = list(client._zenoh.get(Keys("default").pose(broken.session), timeout=10))
        del node.keys.session_of
        err = decode(bytes(reply.err.payload.to_bytes()), Error)
        assert err.code == ErrorCode.INTERNAL and "ZeroDivisionError" in err.message, err
        assert any("_on_pose" in r.getMessage() and r.exc_info for r in caplog.records)
        client.close_session()
        healthy = _open(client, traj, worlds=2)
        for i in range(3):
            client.send(traj.frame(i, healthy.session))
            assert client.latest_pose(timeout=60, after_seq=i).seq == i
        client.close_session()


def test_an_object_from_a_mesh_file_is_tracked_through_the_service_by_a_setting(tmp_path):
    import trimesh

    from inhand_tracker.service.server import ServiceConfig, TrackerNode

    trimesh.creation.box(extents=(40.0, 40.0, 60.0)).export(tmp_path / "block.stl")  # millimetres
    objects = tmp_path / "objects.toml"
    objects.write_text('[block]\nmesh = "block.stl"\nscale = 0.001\nmass = 0.05\nmass_range = [0.02, 0.1]\n')
    traj = Trajectory.load(TRAJECTORY)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = ServiceConfig(listen=(endpoint,), device="cpu", groups=1, objects=str(objects), rate_hz=0)
    with TrackerNode(config), TrackerClient(connect=[endpoint]) as client:
        assert "block" in client.service_info().objects
        p0 = traj.truth.initial_pose.copy()
        p0[2] = 0.03  # resting on the table where the brick was
        info = client.open_session(traj.robot, "block", p0, q0=traj.truth.initial_q, worlds=4)
        for i in range(3):
            client.send(traj.frame(i, info.session))
            estimate = client.latest_pose(timeout=120, after_seq=i)
        assert estimate.status == "tracking" and abs(estimate.pose[2] - 0.03) < 0.005
        client.close_session()


def test_status_says_when_a_session_s_worlds_explore_their_contacts():
    """A session whose lowest cost stays above its contact gate says so in its status; one whose
    gate is closed does not."""
    from inhand_tracker.service.server import ServiceConfig, SessionManager
    from inhand_tracker.sim_backend import load_catalog, load_robot

    traj = Trajectory.load(TRAJECTORY)
    robot = load_robot(ROOT / "configs/robots/allegro.toml")
    manager = SessionManager(ServiceConfig(groups=1, device="cpu", rate_hz=0), {robot.name: robot}, load_catalog())
    gate = {"contacts.contact_worlds": 4, "contacts.contact_gate_updates": 2}
    opened = {}
    for cost in (1e-9, 1e9):
        info = manager.open(
            OpenSession(robot=traj.robot, object=traj.object, p0=traj.truth.initial_pose, q0=traj.truth.initial_q,
                        worlds=4, overrides=gate | {"contacts.contact_gate_cost": cost})
        )  # fmt: skip
        pool = manager.sessions[info.session].pool
        assert not manager.status(info.session, info.token).contacts_explored
        for i in range(60):  # the fingers close on the brick from frame 41
            manager.submit(traj.frame(i, info.session, token=info.token))
            manager.step(pool)
        opened[cost] = manager.status(info.session, info.token).contacts_explored
    assert opened == {1e-9: True, 1e9: False}
