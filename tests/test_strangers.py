"""Caps a stranger cannot spend: on a plain Zenoh network any peer may open under any name with any
number of keys, so the service counts its caps per robot key an open proves, keeps a name that a
key holds for that key, and keeps room for the robots its ``robot_keys`` lists. A listed robot's
open and reopen succeed under every flood a stranger can send; an unlisted robot keeps its names
and its own caps; a recorded open cannot be replayed."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest
from service_process import ServiceProcess, free_port

from inhand_tracker.client import TrackerClient
from inhand_tracker.protocol import ErrorCode, OpenSession, Trajectory, encode
from inhand_tracker.protocol.identity import RobotKey
from inhand_tracker.protocol.keys import Keys
from inhand_tracker.service.paths import DATA_DIR
from inhand_tracker.service.server.config import ServiceConfig
from inhand_tracker.service.server.sessions import ServiceError, SessionManager
from inhand_tracker.sim_backend import load_catalog, load_robot

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def traj() -> Trajectory:
    return Trajectory.load(DATA_DIR / "smoke-foam_brick_pick_place_0.traj")


def _manager(**settings) -> SessionManager:
    robot = load_robot(ROOT / "configs/robots/allegro.toml")
    config = ServiceConfig(**{"groups": 2, "device": "cpu", "rate_hz": 0} | settings)
    return SessionManager(config, {robot.name: robot}, load_catalog())


def _request(traj: Trajectory, **changes) -> OpenSession:
    asked = {"robot": traj.robot, "object": traj.object, "p0": traj.truth.initial_pose, "worlds": 4}
    return OpenSession(**asked | changes)


def _proven(manager: SessionManager, key: RobotKey, request: OpenSession, stamp: float | None = None) -> OpenSession:
    """``request`` as a client holding ``key`` sends it: the key, the service's clock, the proof."""
    keyed = request.model_copy(update={"client_key": key.public, "stamp": time.time() if stamp is None else stamp})
    return key.prove(manager.identity.public, keyed)


def _refused(manager: SessionManager, request: OpenSession, peer: str = "") -> ServiceError:
    with pytest.raises(ServiceError) as exc:
        manager.open(request, peer)
    return exc.value


def test_a_listed_robot_opens_and_reopens_under_any_stranger_s_flood(traj):
    """Strangers flood the service as the attacks did: anonymous opens in a loop, opens under
    rotating names, opens under the robot's own name, and new keys each opening with new settings
    (a population each). They fill their own caps and the room not kept; the listed robot's open,
    its reopen after its session was lost, and an open that needs a population of its own succeed."""
    robot = RobotKey()
    manager = _manager(
        groups=4, max_sessions=12, max_populations=4, max_opens_per_minute=60, max_sessions_per_peer=3,
        reserved_sessions=3, reserved_populations=1, robot_keys={"robot": robot.fingerprint},
    )  # fmt: skip
    opened, refused = [], []
    attacks = [(_request(traj), "")] * 40  # anonymous, in a loop
    attacks += [(_request(traj, name=f"rotating_{i}"), "") for i in range(10)]
    attacks += [(_request(traj), f"name{i}") for i in range(10)]
    for request, peer in attacks:
        try:
            opened.append(manager.open(request, peer))
        except ServiceError as exc:
            refused.append(exc)
    assert len(opened) == 9 and {e.code for e in refused} == {ErrorCode.CAPACITY}  # 12 sessions less the 3 kept
    assert "sessions: 9 open by peers not in robot_keys, their limit is 9" in refused[-1].message
    for _ in range(28):  # under the robot's own name: never its caps, never a session
        exc = _refused(manager, _request(traj), peer="robot")
        assert exc.code == ErrorCode.FORBIDDEN and "peer: 'robot' is held by robot key" in exc.message
        exc = _refused(manager, _proven(manager, RobotKey(), _request(traj)), peer="robot")
        assert exc.code == ErrorCode.FORBIDDEN
    for info in opened[:2]:  # room for sessions again; new keys with new settings want populations
        manager.close(info.session, info.token)
    for seed in range(1, 6):
        exc = _refused(manager, _proven(manager, RobotKey(), _request(traj, overrides={"seed": seed})))
        assert "populations: 3 built for peers not in robot_keys, their limit is 3" in exc.message

    first = manager.open(_proven(manager, robot, _request(traj, name="left_hand")), "robot")
    assert first.session.startswith("robot~")  # a router's rules can confine the robot to its own keys
    manager.drop(first.session)  # lost: its robot's token went, the service restarted its loop, ...
    again = manager.open(_proven(manager, robot, _request(traj, name="left_hand")), "robot")
    assert again.name == "left_hand"
    own = manager.open(_proven(manager, robot, _request(traj, overrides={"seed": 99})), "robot")
    assert own.worlds == 4 and len(manager.pools) == 4


def test_strangers_fill_only_the_frame_budget_not_kept_for_listed_robots(traj, tmp_path):
    """With a frame budget, peers not in ``robot_keys`` may fill the share of it the kept populations
    leave (here 3 of 4: 60 of 80 ms); a listed robot's population still fits in the rest."""
    robot = RobotKey()
    manager = _manager(groups=1, rate_hz=10, min_worlds=4, frame_time_cache=str(tmp_path), max_populations=4,
                       reserved_populations=1, robot_keys={"robot": robot.fingerprint})  # fmt: skip
    manager.frame_times.points = {1: 5.0, 64: 40.0}  # 64 worlds step in 40 ms; the budget: 10 Hz x 0.8 = 80 ms
    first = manager.open(_request(traj, worlds=64, q0=traj.truth.initial_q))
    assert first.worlds == 64  # 40 ms of the 60 strangers may fill
    exc = _refused(manager, _request(traj, worlds=64, q0=traj.truth.initial_q, overrides={"seed": 1}))
    assert "frame budget of 60.0 ms (10 Hz x 0.8 x 0.75 not kept for robot_keys)" in exc.message, exc.message
    listed = manager.open(_proven(manager, robot, _request(traj, worlds=64, q0=traj.truth.initial_q,
                                                           overrides={"seed": 1})), "robot")  # fmt: skip
    assert listed.worlds == 64  # 80 of the whole 80 ms


def test_an_unlisted_robot_keeps_its_names_and_its_own_caps(traj):
    """Without ``robot_keys`` the service keeps no room, but what a key holds is its own: its caps
    count per key (a stranger opening under its peer name spends nothing of it), and its session's
    name and peer name are its key's while the session lives and for the reopen window after."""
    robot, stranger = RobotKey(), RobotKey()
    manager = _manager(max_sessions=16, max_sessions_per_peer=2, max_opens_per_minute_per_peer=4)
    mine = manager.open(_proven(manager, robot, _request(traj, name="arm")), "lab")
    for request in [_request(traj), _proven(manager, stranger, _request(traj))]:
        exc = _refused(manager, request, "lab")
        assert exc.code == ErrorCode.FORBIDDEN
        assert f"peer: 'lab' is held by robot key {robot.fingerprint} (its session)" in exc.message
    assert "name: 'arm' is another open session's" in _refused(manager, _request(traj, name="arm")).message
    for _ in range(2):  # a stranger's own key fills its own caps
        manager.open(_proven(manager, stranger, _request(traj)), "elsewhere")
    exc = _refused(manager, _proven(manager, stranger, _request(traj)), "elsewhere")
    assert f"sessions: 2 open under robot key {stranger.fingerprint}, its limit is 2" in exc.message
    manager.drop(mine.session)  # lost: the names wait for its reopen
    exc = _refused(manager, _request(traj, name="arm"))
    assert exc.code == ErrorCode.FORBIDDEN and "(its session)" in exc.message
    assert manager.open(_proven(manager, robot, _request(traj, name="arm")), "lab").name == "arm"
    # An unnamed session's default name is kept for its key too: a stranger's open is numbered past it.
    other = RobotKey()
    unnamed = manager.open(_proven(manager, other, _request(traj)))
    assert unnamed.name == "allegro_foam_brick"
    manager.drop(unnamed.session)
    assert manager.open(_request(traj)).name == "allegro_foam_brick_2"
    assert manager.open(_proven(manager, other, _request(traj))).name == "allegro_foam_brick"


def test_an_open_proves_its_key_once_and_only_while_it_is_fresh(traj):
    """A recorded open replayed is refused, so is one whose stamp is off the service's clock, one
    whose proof is another key's, and one whose fields were changed after it was proven."""
    robot = RobotKey()
    manager = _manager()
    request = _proven(manager, robot, _request(traj))
    manager.open(request)
    exc = _refused(manager, request)
    assert exc.code == ErrorCode.FORBIDDEN and "proof: this open was sent before (a replay)" in exc.message
    exc = _refused(manager, _proven(manager, robot, _request(traj), stamp=time.time() - 45))
    assert "stamp: " in exc.message and "-45" in exc.message and "the most is 30 s" in exc.message
    stolen = _proven(manager, RobotKey(), _request(traj)).model_copy(update={"client_key": robot.public})
    assert "does not prove its client_key" in _refused(manager, stolen).message
    changed = _proven(manager, robot, _request(traj)).model_copy(update={"worlds": 8})
    assert "does not prove its client_key" in _refused(manager, changed).message


def test_settings_name_each_listed_robot_s_key(tmp_path):
    with pytest.raises(ValueError, match="'arm': expected a robot key's fingerprint, 8 groups of 4 hex digits"):
        ServiceConfig(robot_keys={"arm": "3f2a"})
    key = RobotKey.load_or_create(tmp_path / "robot.key")
    assert RobotKey.load_or_create(tmp_path / "robot.key").public == key.public  # kept
    assert (tmp_path / "robot.key").stat().st_mode & 0o777 == 0o600
    spelled = key.fingerprint.upper().replace("-", ":")
    assert ServiceConfig(robot_keys={"arm": spelled}).robot_keys == {"arm": key.fingerprint}
    printed = subprocess.run([sys.executable, "-m", "inhand_tracker.service.cli", "robot-key", tmp_path / "robot.key"],
                             capture_output=True, text=True, check=True).stdout  # fmt: skip
    assert printed.strip() == key.fingerprint


def _flood(endpoint: str, traj: Trajectory) -> list:
    """A stranger's opens: six under no name, four under the listed robot's; each one's answer."""
    answers = []
    with TrackerClient(connect=[endpoint]) as stranger:
        for peer in [None] * 6 + ["arm"] * 4:
            payload = encode(_request(traj, worlds=2))
            (reply,) = list(stranger._zenoh.get(Keys("default", peer).open, payload=payload, timeout=120))
            answers.append("ok" if reply.ok is not None else bytes(reply.err.payload.to_bytes()))
    return answers


def test_over_zenoh_a_listed_robot_opens_and_reopens_while_a_stranger_floods(traj, tmp_path):
    """A real service with a robot listed by its key's fingerprint; a stranger on the same Zenoh
    network floods opens (anonymous and under the robot's name) until it is refused. The robot, a
    TrackerClient with its key file, opens and tracks; the service is killed and restarted (its key
    and settings kept), the stranger floods the new one first, and the robot's reopen succeeds."""
    port = free_port()
    listed = RobotKey.load_or_create(tmp_path / "robot.key").fingerprint
    settings = dict(key_file=str(tmp_path / "service.key"), max_sessions="4", reserved_sessions="1",
                    robot_keys=f'{{"arm": "{listed}"}}')  # fmt: skip
    svc = ServiceProcess(port, groups=1, timeout_s=5.0, **settings)
    try:
        with TrackerClient(connect=[svc.endpoint], peer="arm", identity=tmp_path / "robot.key") as robot:
            svc.wait_ready(robot)
            answers = _flood(svc.endpoint, traj)
            assert answers[:3] == ["ok"] * 3 and all(b"capacity" in a for a in answers[3:6]), answers
            assert all(b"forbidden" in a and b"held by robot key" in a for a in answers[6:])
            info = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=2,
                                      q0=traj.truth.initial_q)  # fmt: skip
            assert info.session.startswith("arm~") and info.token
            robot.send(traj.frame(0, info.session))
            assert robot.latest_pose(timeout=60, after_seq=0).seq == 0
            svc.proc.kill()
            svc.proc.wait()
            svc = ServiceProcess(port, groups=1, timeout_s=5.0, **settings)
            svc.wait_ready(robot)
            assert _flood(svc.endpoint, traj)[:4] == ["ok"] * 3 + [answers[3]]  # the stranger came back first
            again = robot.reopen()
            assert again.session != info.session
            robot.send(traj.frame(0, again.session))
            assert robot.latest_pose(timeout=60, after_seq=0).seq == 0
    finally:
        svc.stop()
