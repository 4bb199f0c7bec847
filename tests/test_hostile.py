"""What a hostile or broken peer sends must not stop the service, leak a session or poison another
robot's tracking: bad opens refused at the boundary with nothing left behind, a seq that jumps
re-synchronises the session, a flooding robot keeps only its newest frames, and the client tells
its caller when the estimate it holds is stale or the service went away."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from pydantic import ValidationError
from service_process import ServiceProcess, free_port

from inhand_tracker.client import ServiceLost, StaleEstimate, TrackerClient, TrackerError, zenoh_config
from inhand_tracker.protocol import (
    CloseSession,
    Error,
    ErrorCode,
    Keys,
    OpenSession,
    PoseObservation,
    RobotFrame,
    SessionInfo,
    Trajectory,
    decode,
    encode,
)
from inhand_tracker.protocol.auth import sign, signed_query
from inhand_tracker.service.paths import DATA_DIR
from inhand_tracker.service.server.config import ServiceConfig
from inhand_tracker.service.server.sessions import ServiceError, SessionManager
from inhand_tracker.sim_backend import load_catalog, load_robot

TRAJECTORY = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def traj() -> Trajectory:
    return Trajectory.load(TRAJECTORY)


def _manager(**settings) -> SessionManager:
    robot = load_robot(ROOT / "configs/robots/allegro.toml")
    config = ServiceConfig(**{"groups": 2, "device": "cpu", "rate_hz": 0} | settings)
    return SessionManager(config, {robot.name: robot}, load_catalog())


def _request(traj: Trajectory, **changes) -> OpenSession:
    return OpenSession(robot=traj.robot, object=traj.object, p0=traj.truth.initial_pose, worlds=4, **changes)


@pytest.mark.parametrize(
    "quaternion, length",
    [((0, 0, 0, 0), "0"), ((1e-30, 0, 0, 0), "1e-30"), ((3e38, 3e38, 0, 0), "4.24e+38")],
)
def test_an_open_whose_quaternion_has_no_direction_is_refused_naming_it(traj, quaternion, length):
    p0 = np.concatenate([traj.truth.initial_pose[:3], quaternion])
    with pytest.raises(ValidationError) as exc:
        OpenSession(robot=traj.robot, object=traj.object, p0=p0)
    assert "p0" in str(exc.value) and f"length {length}" in str(exc.value)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_overrides_are_refused_at_the_boundary(traj, value):
    with pytest.raises(ValidationError) as exc:
        _request(traj, overrides={"estimate_lambda": value})
    assert "overrides" in str(exc.value) and "estimate_lambda" in str(exc.value)


def test_a_refused_open_leaves_no_session_and_builds_nothing(traj):
    manager = _manager()
    for overrides, words in [({"update_every": 0}, "update_every"), ({"seeding.sigma_t": -1.0}, "seeding.sigma_t")]:
        with pytest.raises(ServiceError) as exc:
            manager.open(_request(traj, overrides=overrides))
        assert exc.value.code == ErrorCode.BAD_REQUEST and words in exc.value.message
    assert manager.sessions == {} and manager.pools == {}


def test_a_seq_jump_resynchronises_the_session_and_says_so(traj):
    manager = _manager(seq_window=100)
    info = manager.open(_request(traj))
    pool = manager.sessions[info.session].pool
    for seq in range(3):
        manager.submit(traj.frame(seq, info.session, token=info.token))
        manager.step(pool)
    manager.submit(traj.frame(3, info.session, token=info.token, seq=2**31))  # a corrupt seq
    (est,) = manager.step(pool)
    assert est.seq == 2**31 and "2147483648 after 2, beyond the service's window of 100" in est.notice  # told
    for seq in (7, 8):  # the robot's own counter again: far behind, so a second re-sync, then in order
        manager.submit(traj.frame(seq, info.session, token=info.token, seq=seq))
        (est,) = manager.step(pool)
        assert est.seq == seq and (est.notice is not None) == (seq == 7)  # said once
    status = manager.status(info.session, info.token)
    assert (status.frames, status.resyncs, status.late) == (6, 2, 0)
    assert "RobotFrame.seq: 7 after 2147483648" in status.last_error
    manager.submit(traj.frame(9, info.session, token=info.token, seq=5))  # within the window behind: late, dropped
    status = manager.status(info.session, info.token)
    assert status.late == 1 and "RobotFrame.seq: 5 is behind the session's 8: dropped as late" in status.last_error


def test_a_stray_seq_within_the_window_never_silences_the_robot(traj):
    """One frame's seq ran 250 ahead (inside the window, so taken as a gap); the robot's own
    counter goes on behind it. After ``late_resync`` late frames the session takes the robot's
    counter again, says so, and tracks every frame after."""
    manager = _manager(seq_window=300, late_resync=5)
    info = manager.open(_request(traj))
    pool = manager.sessions[info.session].pool
    frame = lambda i, seq: traj.frame(i, info.session, token=info.token, seq=seq)  # noqa: E731
    for seq in range(3):
        manager.submit(frame(seq, seq))
        manager.step(pool)
    manager.submit(frame(3, 253))
    manager.step(pool)
    estimates = []
    for seq in range(4, 20):
        manager.submit(frame(seq, seq))
        estimates += manager.step(pool) if manager.ready(0.0) else []
    status = manager.status(info.session, info.token)
    assert (status.late, status.resyncs) == (4, 1), status
    assert [e.seq for e in estimates] == list(range(8, 20)), "tracked again from the fifth frame behind"
    assert "5 frames in a row behind it: re-synchronised" in estimates[0].notice


def test_a_relay_replaying_a_robot_s_signed_messages_applies_none_of_them(traj):
    """Everything a signed robot sends is fresh or refused: recorded frames replayed behind the
    session (near, far, or many in a row) never re-synchronise it, a restart of the robot's own
    counter (a new epoch) does and the old epoch's frames stay refused, and a replayed observation
    or status query is refused and counted."""
    manager = _manager(seq_window=100, late_resync=5)
    info = manager.open(_request(traj))
    pool = manager.sessions[info.session].pool
    signed = lambda i, seq=None, epoch=0: sign(  # noqa: E731
        traj.frame(i, info.session, seq=seq).model_copy(update={"epoch": epoch}), info.token
    )
    recorded = [signed(i) for i in range(10)]
    for frame in recorded:
        manager.submit(frame)
        manager.step(pool)
    for frame in recorded * 2:  # a relay plays its recording back, twenty frames behind in a row
        manager.submit(frame)
    status = manager.status_of(manager.sessions[info.session])
    assert not manager.ready(0.0) and (status.frames, status.resyncs) == (10, 0), status
    assert status.replays == 16 and "refused as a replay" in status.last_error, status
    manager.submit(signed(10, seq=500))  # the robot's own counter jumps ahead: followed
    (est,) = manager.step(pool)
    assert est.seq == 500 and "beyond the service's window" in est.notice
    manager.submit(recorded[3])  # far behind in the same epoch: a replay, not a re-sync
    assert not manager.ready(0.0)
    manager.submit(signed(11, seq=0, epoch=1))  # the robot restarts its counter: a new epoch
    (est,) = manager.step(pool)
    assert est.seq == 0 and "epoch 1: the robot restarted its counter" in est.notice
    for frame in recorded[:3]:  # the old epoch's frames, replayed
        manager.submit(frame)
    observation = sign(
        PoseObservation(session=info.session, stamp=1.0, pose=traj.truth.pose[0], covariance=np.eye(6) * 1e-4),
        info.token,
    )
    manager.observe(observation)
    manager.observe(observation)  # the same again
    query = signed_query(CloseSession(session=info.session), info.token, "status")
    manager.authorize_query(query, "status")
    with pytest.raises(ServiceError, match=r"not newer than .* accepted: refused as a replay"):
        manager.authorize_query(query, "status")
    status = manager.status_of(manager.sessions[info.session])
    assert (status.frames, status.resyncs, status.replays) == (12, 2, 22), status
    # What the robot sends is what the status says the best world leaves unexplained: joints and forces.
    assert set(status.residuals) == {"joints", "force"} and status.evidence == 1.0, status
    assert len(manager.sessions[info.session].observed) == 1


def test_one_far_future_stamp_does_not_make_later_observations_stale(traj):
    manager = _manager(max_observation_age_s=0.5)
    info = manager.open(_request(traj))
    pool = manager.sessions[info.session].pool
    manager.submit(traj.frame(0, info.session, token=info.token).model_copy(update={"stamp": 1e9}))
    manager.step(pool)
    for seq in (1, 2):
        manager.submit(traj.frame(seq, info.session, token=info.token))
        manager.step(pool)
    seen = PoseObservation(session=info.session, token=info.token, stamp=traj.stamp[2], pose=traj.truth.pose[2],
                           covariance=np.eye(6) * 1e-4)  # fmt: skip
    manager.observe(seen)
    manager.submit(traj.frame(3, info.session, token=info.token))
    manager.step(pool)
    status = manager.status(info.session, info.token)
    assert (status.observations, status.observations_stale) == (1, 0), status


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda t, p0: RobotFrame(session="s", seq=0, stamp=float("nan"), controls=t, q=t), "stamp"),
        (lambda t, p0: RobotFrame(session="s", seq=0, stamp=1e300, controls=t, q=t), "stamp"),
        (lambda t, p0: RobotFrame(session="s", seq=0, stamp=-1.0, controls=t, q=t), "stamp"),
        (lambda t, p0: RobotFrame(session="s", seq=0, stamp=0.0, controls={"a": {"b": 1}}, q=t), "controls"),
        (lambda t, p0: OpenSession(robot="r", object="o", p0=np.r_[1e30, p0[1:]]), "p0"),
        (lambda t, p0: OpenSession(robot="r", object="o", p0=p0, worlds=True), "worlds"),
        (
            lambda t, p0: PoseObservation(session="s", stamp=0.0, pose=np.r_[0, 0, 1e30, p0[3:]], covariance=np.eye(6)),
            "pose",
        ),
    ],
)
def test_out_of_range_values_are_refused_at_the_boundary_naming_the_field(traj, make, field):
    with pytest.raises(ValidationError) as exc:
        make(np.zeros(22, np.float32), traj.truth.initial_pose)
    assert exc.value.errors()[0]["loc"][0] == field, exc.value


@pytest.mark.parametrize(
    "overrides, words",
    [({"recovery.recover_frames": -5}, "recovery.recover_frames: expected >= 0 frames, got -5"),
     ({"seeding.mass_sigma0": 1e30}, "seeding.mass_sigma0: expected 0 to 1, got 1e+30"),
     ({"update_every": 0}, "update_every: expected 1 to 10000 frames, got 0")],
)  # fmt: skip
def test_settings_out_of_their_range_are_refused_naming_them(traj, overrides, words):
    with pytest.raises(ServiceError, match=re.escape(f"overrides: {words}")):
        _manager().open(_request(traj, overrides=overrides))


def test_settings_are_overridden_by_their_dotted_names_and_no_other_spelling(traj):
    manager = _manager()
    dotted = {"optimizer.min_separation": 4, "optimizer.reps_epsilon": 0.25}
    info = manager.open(_request(traj, method="REPS", overrides=dotted))
    optimizer = manager.sessions[info.session].pool.tracker.config.optimizer
    assert (optimizer.method, optimizer.min_separation, optimizer.reps_epsilon) == ("REPS", 4.0, 0.25)
    with pytest.raises(ServiceError, match=re.escape("overrides: optimizer.min_separation: expected >= 0, got -1.0")):
        manager.open(_request(traj, overrides={"optimizer.min_separation": -1}))
    with pytest.raises(ServiceError, match=re.escape("'min_separation' is 'optimizer.min_separation'")):
        manager.open(_request(traj, overrides={"min_separation": 4}))
    with pytest.raises(ServiceError, match=re.escape("overrides: unknown ['population.impratio']")):
        manager.open(_request(traj, overrides={"population.impratio": 3}))  # the service's physics, not a session's


def test_a_robots_config_gives_its_sessions_their_settings_which_overrides_change(traj, tmp_path):
    config, base = tmp_path / "allegro.toml", f'extends = "{ROOT / "configs/robots/allegro.toml"}"\n'
    config.write_text(base + "[tracker.optimizer]\nopen_loop_ratio = 2.0\n")
    robot = load_robot(config)
    manager = SessionManager(ServiceConfig(groups=2, device="cpu", rate_hz=0), {robot.name: robot}, load_catalog())
    said = [manager.open(_request(traj, method="REPS", overrides=o)) for o in ({}, {"optimizer.open_loop_ratio": 0})]
    ratios = [manager.sessions[info.session].pool.tracker.config.optimizer.open_loop_ratio for info in said]
    assert ratios == [2.0, 0.0]
    config.write_text(base + "[tracker]\nopen_loop_ratoi = 2.0\n")
    with pytest.raises(ValueError, match=r"robot 'allegro' tracker: no setting 'open_loop_ratoi'"):
        SessionManager(ServiceConfig(device="cpu", rate_hz=0), {robot.name: load_robot(config)}, load_catalog())


def test_each_estimate_says_how_far_its_pose_is_dead_reckoning(traj):
    """OLP is dead reckoning; a population reports none of it by default, and its open-loop world's
    pose under ``optimizer.open_loop_ratio`` while no world explains the robot better (here every
    world's costs, before the hand closes, are alike)."""
    manager = _manager(groups=3)
    settings = {"OLP": {}, "REPS": {}, "ratio": {"optimizer.open_loop_ratio": 10.0}}
    infos = {
        name: manager.open(_request(traj, method="REPS" if name == "ratio" else name, overrides=overrides))
        for name, overrides in settings.items()
    }
    names = {info.session: name for name, info in infos.items()}
    said = {name: [] for name in infos}
    for i in range(3):
        for info in infos.values():
            manager.submit(traj.frame(i, info.session, token=info.token))
        pools = {id(pool): pool for pool in (manager.sessions[session].pool for session in names)}
        for pool in pools.values():
            for est in manager.step(pool):
                said[names[est.session]].append(est.dead_reckoning)
    assert said == {"OLP": [1.0] * 3, "REPS": [0.0] * 3, "ratio": [1.0] * 3}, said


def test_a_peer_sharing_the_population_cannot_poison_it(traj):
    """An attacker opens with the victim's robot, object and K (so it joins the victim's population)
    and sends joints of 1e20 rad: refused at the boundary, naming the joint; the victim's estimates
    are bit for bit those of a run without the attacker."""

    def victim_run(attack: bool) -> list[np.ndarray]:
        manager = _manager()
        victim = manager.open(_request(traj))
        pool = manager.sessions[victim.session].pool
        if attack:
            attacker = manager.open(_request(traj))
            assert manager.sessions[attacker.session].pool is pool
        poses = []
        for i in range(6):
            if attack and i in (1, 2, 3):
                frame = traj.frame(i, attacker.session, token=attacker.token)
                with pytest.raises(ServiceError, match=r"RobotFrame.q: joint '.*' = 1e\+20 lies outside its limits"):
                    manager.submit(frame.model_copy(update={"q": np.full_like(frame.q, 1e20)}))
            manager.submit(traj.frame(i, victim.session, token=victim.token))
            (estimate,) = [e for e in manager.step(pool) if e.session == victim.session]
            poses.append(estimate.pose)
        assert manager.status(victim.session, victim.token).errors == 0
        return poses

    for alone, attacked in zip(victim_run(False), victim_run(True), strict=True):
        assert np.array_equal(alone, attacked)


@pytest.mark.slow
def test_memory_stays_flat_over_a_thousand_open_close_cycles(traj):
    """A robot (or a peer) opening and closing in a loop: the service's resident memory after 1,000
    cycles is within 1 % of what it was after the first 200 (the population stays, held by a session)."""
    import gc

    manager = _manager(max_opens_per_minute=100_000)
    manager.open(_request(traj))  # keeps the population: the cycles reuse its other group

    def resident_kib() -> float:
        gc.collect()
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1024

    for cycle in range(1000):
        info = manager.open(_request(traj))
        manager.close(info.session, info.token)
        if cycle == 199:
            warm = resident_kib()
    grown = resident_kib() - warm
    assert grown < 0.01 * warm, f"{grown:.0f} KiB more after 800 cycles ({warm:.0f} KiB resident)"
    assert len(manager.sessions) == 1 and len(manager.pools) == 1


def test_a_session_s_name_is_its_own(traj):
    """A name names the session's ROS 2 topics and TF frame: another open session's is refused; a
    name may carry a namespace; unnamed, a session's name is the same on every run (the robot's
    peer name, its robot and object). Where names are ROS 2 topics, a second one that would take
    it is refused, not numbered by whichever opened first; without ROS 2 it is numbered."""
    manager = _manager(groups=6, ros2=True)
    named = manager.open(_request(traj, name="left_hand"))
    with pytest.raises(ServiceError, match="name: 'left_hand' is another open session's"):
        manager.open(_request(traj, name="left_hand"))
    assert manager.open(_request(traj)).name == "allegro_foam_brick"
    with pytest.raises(ServiceError, match="default name 'allegro_foam_brick' is another session's ROS 2 topic"):
        manager.open(_request(traj))
    assert manager.open(_request(traj), peer="cell-2.arm").name == "cell_2_arm/allegro_foam_brick"
    assert manager.open(_request(traj, name="lab2/left_hand")).name == "lab2/left_hand"
    manager.close(named.session, named.token)
    assert manager.open(_request(traj, name="left_hand")).name == "left_hand"
    for bad in ("2nd hand", "lab2/", "/left", "lab2//left", "lab2/2nd"):  # not ROS names
        with pytest.raises(ValidationError, match="name"):
            _request(traj, name=bad)
    plain = _manager(groups=2)  # no ROS 2 topics: the name only labels the session
    assert [plain.open(_request(traj)).name for _ in range(2)] == ["allegro_foam_brick", "allegro_foam_brick_2"]


def test_a_megabyte_of_garbage_on_a_session_key_does_not_break_its_status(traj):
    manager = _manager()
    info = manager.open(_request(traj))
    manager.count_error(info.session, "x" * (1 << 20))
    status = manager.status(info.session, info.token)
    assert status.errors == 1 and len(status.last_error) <= 500 and status.last_error.endswith("...")
    assert len(encode(status)) < 4096


def test_a_flooding_robot_keeps_its_newest_frames_and_the_rest_are_counted(traj):
    manager = _manager(max_pending=5, max_frame_age_s=0.5)
    flood = manager.open(_request(traj))
    calm = manager.open(_request(traj))
    pool = manager.sessions[flood.session].pool
    for seq in range(50):
        manager.submit(traj.frame(seq, flood.session, token=flood.token))
    manager.submit(traj.frame(0, calm.session, token=calm.token))
    estimates = {e.session: e for e in manager.step(pool)}
    assert estimates[flood.session].seq == 45 and estimates[calm.session].seq == 0  # one frame each
    assert manager.status(flood.session, flood.token).stale == 45
    # Frames that waited past the bound are skipped, up to the newest.
    for seq in range(1, 4):
        manager.submit(traj.frame(seq, calm.session, token=calm.token), received=time.perf_counter() - 1.0)
    manager.submit(traj.frame(4, calm.session, token=calm.token))
    estimates = {e.session: e for e in manager.step(pool)}
    assert estimates[calm.session].seq == 4 and manager.status(calm.session, calm.token).stale == 3
    assert estimates[flood.session].seq == 46  # the flood's queue drains in order, one frame a tick


@pytest.fixture(scope="module")
def service():
    svc = ServiceProcess(free_port(), timeout_s=1.0)
    with TrackerClient(connect=[svc.endpoint]) as probe:
        svc.wait_ready(probe)
    yield svc
    svc.stop()


def test_bad_opens_over_zenoh_are_answered_and_the_service_goes_on(service, traj):
    keys = Keys("default")
    with TrackerClient(connect=[service.endpoint]) as client:
        raw = msgpack.unpackb(encode(_request(traj)), raw=False)
        for field, value in [("overrides", {"estimate_lambda": float("nan")}), ("p0", None)]:
            bad = dict(raw)
            if field == "p0":
                bad["p0"] = dict(raw["p0"], data=np.array([0, 0, 0.1, 0, 0, 0, 0], np.float32).tobytes())
            else:
                bad[field] = value
            (reply,) = list(client._zenoh.get(keys.open, payload=msgpack.packb(bad, use_bin_type=True), timeout=30))
            err = decode(bytes(reply.err.payload.to_bytes()), Error)
            assert err.code == ErrorCode.BAD_REQUEST and f"OpenSession.{field}" in err.message, err
        assert client.service_info().sessions == 0  # nothing leaked
        info = client.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4)
        client.send(traj.frame(0, info.session))
        assert client.latest_pose(timeout=60, after_seq=0).seq == 0


def test_the_client_flags_a_stale_estimate_and_a_lost_service(traj):
    svc = ServiceProcess(free_port(), timeout_s=1.0)
    with TrackerClient(connect=[svc.endpoint]) as client:
        svc.wait_ready(client)
        info = client.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4)
        client.send(traj.frame(0, info.session))
        assert client.latest_pose(timeout=60, after_seq=0, max_age=0.5).seq == 0
        svc.proc.send_signal(signal.SIGSTOP)  # the service stalls
        try:
            client.send(traj.frame(1, info.session).model_copy(update={"stamp": 1.0}))
            with pytest.raises(StaleEstimate, match=r"answers seq 0 .* 1.000 s behind the last frame sent \(seq 1\)"):
                client.latest_pose(timeout=0.2, max_age=0.5)
            assert client.latest_pose(timeout=0.2).seq == 0  # without a bound: the cached estimate, as before
        finally:
            svc.proc.send_signal(signal.SIGCONT)
        assert client.latest_pose(timeout=60, after_seq=1, max_age=0.5).seq == 1
        svc.stop()
        with pytest.raises(ServiceLost, match="went away"):
            client.latest_pose(timeout=10.0, after_seq=10**6)


def test_caps_refuse_with_the_numbers_and_an_emptied_population_is_freed(traj):
    manager = _manager(max_sessions=2, max_populations=1)
    a = manager.open(_request(traj))
    with pytest.raises(ServiceError) as exc:  # another K needs a second population
        manager.open(_request(traj).model_copy(update={"worlds": 8}))
    assert exc.value.code == ErrorCode.CAPACITY
    assert "populations: 1 built, this service's limit is 1" in exc.value.message
    b = manager.open(_request(traj))
    with pytest.raises(ServiceError) as exc:
        manager.open(_request(traj))
    assert exc.value.code == ErrorCode.CAPACITY and "sessions: 2 open, this service's limit is 2" in exc.value.message
    manager.close(a.session, a.token)
    assert len(manager.pools) == 1  # b still tracks in it
    manager.close(b.session, b.token)
    assert manager.pools == {}  # its memory and worlds go back
    info = manager.open(_request(traj).model_copy(update={"worlds": 8}))
    assert info.worlds == 8 and len(manager.pools) == 1
    manager = _manager(max_opens_per_minute=2)
    for _ in range(2):
        manager.open(_request(traj))
    with pytest.raises(ServiceError) as exc:
        manager.open(_request(traj))
    assert exc.value.code == ErrorCode.CAPACITY
    assert "opens: 2 in the last 60 s, this service's limit is 2" in exc.value.message


def test_one_peer_spends_its_own_caps_and_leaves_the_others_theirs(traj):
    """A peer that opens in a loop under its name fills its own session slots and per-minute
    allowance, refused with the numbers; another robot's first open, and a reopen of its own,
    still succeed."""
    manager = _manager(max_sessions=8, max_sessions_per_peer=3, max_opens_per_minute_per_peer=5)
    flood = [manager.open(_request(traj), peer="flood") for _ in range(3)]
    with pytest.raises(ServiceError) as exc:
        manager.open(_request(traj), peer="flood")
    assert exc.value.code == ErrorCode.CAPACITY
    assert "sessions: 3 open under peer 'flood', its limit is 3 (max_sessions_per_peer)" in exc.value.message
    robot = manager.open(_request(traj), peer="robot")
    for info in flood[:2]:  # closing and reopening spends the per-minute allowance
        manager.close(info.session, info.token)
        manager.open(_request(traj), peer="flood")
    manager.close(flood[2].session, flood[2].token)
    with pytest.raises(ServiceError) as exc:
        manager.open(_request(traj), peer="flood")
    assert "opens: 5 under peer 'flood' in the last 60 s, its limit is 5" in exc.value.message
    manager.close(robot.session, robot.token)  # the robot lost its session: it opens again
    assert manager.open(_request(traj), peer="robot").session
    assert manager.open(_request(traj)).session  # an open under no name counts against the service's caps


def test_a_peer_that_opens_with_new_settings_each_time_is_refused_past_its_builds(traj):
    """Every open with settings no population has builds one, and builds take turns with the
    running sessions' steps: past its per-minute builds a peer is refused with the numbers, while
    it may still open where a population has room, and another robot still builds."""
    manager = _manager(max_builds_per_minute_per_peer=2)
    opened = [manager.open(_request(traj, overrides={"seed": s}), peer="churn") for s in (1, 2)]
    with pytest.raises(ServiceError) as exc:
        manager.open(_request(traj, overrides={"seed": 3}), peer="churn")
    assert exc.value.code == ErrorCode.CAPACITY
    assert "builds: 2 populations built for peer 'churn' in the last 60 s, its limit is 2" in exc.value.message
    assert len(manager.pools) == 2  # the refused open built nothing
    assert manager.open(_request(traj, overrides={"seed": 1}), peer="churn").session  # a population with room
    assert manager.open(_request(traj, overrides={"seed": 3}), peer="robot").session
    for info in opened:
        manager.close(info.session, info.token)


def test_sessions_without_a_robot_token_or_frames_are_closed(traj):
    svc = ServiceProcess(free_port(), groups=2, timeout_s=1.0, idle_timeout_s="3")  # one population
    keys = Keys("default")
    try:
        with TrackerClient(connect=[svc.endpoint]) as client:
            svc.wait_ready(client)
            # A peer that opens over the raw protocol and never declares its robot's token:
            (reply,) = list(client._zenoh.get(keys.open, payload=encode(_request(traj)), timeout=60))
            assert reply.ok is not None
            # A robot with its token that never sends a frame:
            client.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4)
            assert client.service_info().sessions == 2
            deadline = time.monotonic() + 1.0 + 2.0
            while time.monotonic() < deadline and client.service_info().sessions > 1:
                time.sleep(0.1)
            assert client.service_info().sessions == 1  # the tokenless one, after robot_timeout_s
            deadline = time.monotonic() + 3.0 + 2.0
            while time.monotonic() < deadline and client.service_info().sessions > 0:
                time.sleep(0.1)
            assert client.service_info().sessions == 0  # the silent one, after idle_timeout_s
    finally:
        svc.stop()


def test_a_flooding_peer_does_not_starve_another_session(traj):
    """One robot streams at 10 Hz, alone and then beside a peer (its own process, as a robot is)
    that floods its own session at 300 Hz, far past what the service steps on this CPU: it keeps at
    least 80 % of its estimate rate, and the flood's backlog stays bounded (counted stale). The
    flood is paced: a peer spinning a core of this 2-core machine would starve every process on
    it, which is the machine's limit, not the service's."""
    svc = ServiceProcess(free_port(), groups=2)
    seconds, rate = 4.0, 10.0

    def stream(client: TrackerClient, start: int) -> int:
        got: list[int] = []
        client.on_pose(lambda est: got.append(est.seq))
        t0 = time.perf_counter()
        n = 0
        while time.perf_counter() - t0 < seconds:
            time.sleep(max(0.0, t0 + n / rate - time.perf_counter()))
            client.send(traj.frame(n % traj.frames, client.info.session, seq=start + n))
            n += 1
        time.sleep(0.5)
        return len(got)

    flooding = textwrap.dedent(f"""
        import json, sys, time
        from inhand_tracker.client import TrackerClient
        from inhand_tracker.protocol import Trajectory
        traj = Trajectory.load({str(TRAJECTORY)!r})
        with TrackerClient(connect=[{svc.endpoint!r}]) as flood:
            info = flood.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q,
                                      worlds=4)
            print("open", flush=True)
            sys.stdin.readline()
            n = 0
            began = time.monotonic()
            while time.monotonic() < began + {seconds}:
                flood.send(traj.frame(n % traj.frames, info.session, seq=n))
                n += 1
                time.sleep(max(0.0, began + n / 300 - time.monotonic()))
            status = flood.status()
            print(json.dumps({{"stale": status.stale, "frames": status.frames, "sent": n}}), flush=True)
    """)
    flood = None
    try:
        with TrackerClient(connect=[svc.endpoint]) as robot:
            svc.wait_ready(robot)
            robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4)
            flood = subprocess.Popen(
                [sys.executable, "-c", flooding], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT
            )
            assert flood.stdout.readline().strip() == "open"
            alone = stream(robot, 0)
            flood.stdin.write("go\n")
            flood.stdin.flush()
            beside = stream(robot, 10_000)
            status = json.loads(flood.stdout.readline())
            assert alone >= 0.8 * rate * seconds, alone
            assert beside >= 0.8 * alone, (alone, beside)
            # Past what the service steps: frames were dropped as stale, and only the rest stepped.
            assert status["stale"] > 0 and status["frames"] + status["stale"] <= status["sent"], status
    finally:
        if flood is not None:
            flood.kill()
            flood.wait()
        svc.stop()


def _certificates(folder: Path) -> dict[str, Path]:
    """The lab's CA and certificates from docker/tls/make-certs.sh: the router's (a TLS server's),
    the service's, a robot's and an observer's, for 127.0.0.1."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make test certificates")
    script = ROOT / "docker/tls/make-certs.sh"
    subprocess.run(["bash", script, folder, "127.0.0.1", "robot", "observer"], check=True, capture_output=True)
    return {p.name: p for p in folder.glob("*.crt")} | {p.name: p for p in folder.glob("*.key")}


def _kept_out(endpoint: str, zenoh_file: Path | None = None) -> None:
    """A peer on ``endpoint`` gets no answer from the service (refused by TLS or by a rule)."""
    with TrackerClient(connect=[endpoint], zenoh_file=zenoh_file) as peer:
        with pytest.raises(TimeoutError):
            peer.service_info(timeout=3.0)


def test_mtls_admits_robots_with_a_certificate_and_access_control_denies_a_key(traj, tmp_path):
    """Only peers with a certificate from the lab's CA connect; among them, an access-control rule
    keeps the observer's certificate from querying anything under the service's keys."""
    certs = _certificates(tmp_path)

    def zenoh_file(name: str, extra: dict | None = None, **tls) -> Path:
        path = tmp_path / f"{name}.json5"
        tls = {k: str(certs[v]) if isinstance(v, str) else v for k, v in tls.items()}
        path.write_text(json.dumps({"transport": {"link": {"tls": tls}}} | (extra or {})))
        return path

    acl = {"access_control": {
        "enabled": True, "default_permission": "allow",
        "rules": [{"id": "no-queries", "messages": ["query"], "flows": ["ingress"], "permission": "deny",
                   "key_exprs": ["inhand/v7/default/**"]}],
        "subjects": [{"id": "observers", "cert_common_names": ["observer"]}],
        "policies": [{"rules": ["no-queries"], "subjects": ["observers"]}],
    }}  # fmt: skip
    service_conf = zenoh_file("service", acl, listen_certificate="router.crt", listen_private_key="router.key",
                              root_ca_certificate="ca.crt", enable_mtls=True)  # fmt: skip
    observer_conf = zenoh_file("observer", root_ca_certificate="ca.crt", enable_mtls=True,
                               connect_certificate="observer.crt", connect_private_key="observer.key")  # fmt: skip
    robot_conf = zenoh_file("robot", root_ca_certificate="ca.crt", enable_mtls=True,
                            connect_certificate="robot.crt", connect_private_key="robot.key")  # fmt: skip
    stranger_conf = zenoh_file("stranger", root_ca_certificate="ca.crt")  # trusts the service, has no certificate
    svc = ServiceProcess(free_port(), scheme="tls", zenoh_config=str(service_conf))
    try:
        with TrackerClient(connect=[svc.endpoint], zenoh_file=robot_conf) as robot:
            svc.wait_ready(robot)
            info = robot.open_session(
                traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4
            )
            robot.send(traj.frame(0, info.session))
            assert robot.latest_pose(timeout=60, after_seq=0).seq == 0
            with TrackerClient(connect=[svc.endpoint], zenoh_file=observer_conf) as observer:
                with pytest.raises(TimeoutError):
                    observer.service_info(timeout=3.0)  # denied by the rule
                seen = []  # connected all the same: what the rule allows still flows
                watch = observer._zenoh.declare_subscriber(Keys("default").every("pose"), seen.append)
                time.sleep(0.5)
                robot.send(traj.frame(1, info.session))
                robot.latest_pose(timeout=60, after_seq=1)
                deadline = time.monotonic() + 5.0
                while not seen and time.monotonic() < deadline:
                    time.sleep(0.05)
                watch.undeclare()
                assert seen
            _kept_out(svc.endpoint, stranger_conf)
            _kept_out(svc.endpoint.replace("tls/", "tcp/"))
    finally:
        svc.stop()


def test_a_peer_without_the_session_token_can_neither_steer_query_status_nor_close_it(service, traj):
    with TrackerClient(connect=[service.endpoint]) as robot, TrackerClient(connect=[service.endpoint]) as peer:
        info = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4)
        robot.send(traj.frame(0, info.session))
        robot.latest_pose(timeout=60, after_seq=0)
        keys, guess = Keys("default"), CloseSession(session=info.session, token="0" * 32)
        # A frame on the session's key with the wrong token is refused, and its robot is told.
        peer._zenoh.put(keys.frame(info.session), encode(traj.frame(5, info.session, token="0" * 32)))
        deadline = time.monotonic() + 10
        while (status := robot.status()).errors < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert status.frames == 1 and "RobotFrame.mac: not the session's robot's" in status.last_error
        for key in (keys.status(info.session), keys.close):
            (reply,) = list(peer._zenoh.get(key, payload=encode(guess), timeout=30))
            assert decode(bytes(reply.err.payload.to_bytes()), Error).code == ErrorCode.FORBIDDEN, key
        robot.send(traj.frame(1, info.session))  # the robot's own session goes on
        assert robot.latest_pose(timeout=60, after_seq=1).seq == 1
        robot.close_session()


def test_a_peer_that_reads_every_frame_and_catches_every_query_learns_no_secret(service, traj):
    """A sniffer subscribed to every session key, and a peer answering status and close queries in
    the service's place: after the open the token never travels, so neither sees it, frames the
    sniffer re-signs with what it saw are refused, and those it replays as they were apply none;
    the robot restarting its own counter is followed."""
    with TrackerClient(connect=[service.endpoint]) as robot, TrackerClient(connect=[service.endpoint]) as peer:
        keys, seen = Keys("default"), []
        peer._zenoh.declare_subscriber(keys.every("*"), lambda s: seen.append(bytes(s.payload.to_bytes())))
        caught = []

        def impostor(query: zenoh.Query) -> None:
            caught.append(bytes(query.payload.to_bytes()) if query.payload else b"")

        rogue = [peer._zenoh.declare_queryable(k, impostor) for k in (keys.every("status"), keys.close)]
        info = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4)
        for i in range(5):
            robot.send(traj.frame(i, info.session))
            robot.observe_pose(traj.truth.pose[i], np.eye(6) * 1e-4)
            robot.latest_pose(timeout=60, after_seq=i)
        status = robot.status()
        time.sleep(0.5)
        frames = [p for p in seen if b"controls" in p]
        assert len(frames) >= 5 and caught, (len(frames), len(caught))
        token = info.token.encode()
        assert not any(token in payload for payload in seen + caught), "the session's token travelled"
        stolen = decode(frames[-1], RobotFrame)
        forged = stolen.model_copy(update={"seq": 9, "controls": stolen.controls + 0.1})  # its old mac
        peer._zenoh.put(keys.frame(info.session), encode(forged))
        deadline = time.monotonic() + 10
        while (after := robot.status()).errors <= status.errors and time.monotonic() < deadline:
            time.sleep(0.05)
        assert after.errors == status.errors + 1 and after.frames == status.frames
        for payload in frames * 4:  # the sniffer replays what it recorded, signed by the robot
            peer._zenoh.put(keys.frame(info.session), payload)
        replayed = lambda s: s.late + s.duplicates + s.replays  # noqa: E731
        while replayed(after := robot.status()) < replayed(status) + 4 * len(frames) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert after.frames == status.frames and after.replays >= 4 * len(frames) - 15, after
        robot.send(traj.frame(0, info.session))  # the robot restarts its own counter: followed
        while (after := robot.status()).frames == status.frames and time.monotonic() < deadline + 30:
            time.sleep(0.05)
        assert (after.frames, after.resyncs) == (status.frames + 1, status.resyncs + 1), after
        for q in rogue:
            q.undeclare()
        robot.close_session()


@pytest.mark.parametrize("where", ["embedded", "running"])
def test_bench_load_reports_every_session_and_the_memory(service, where):
    from typer.testing import CliRunner

    from inhand_tracker.service.cli import app

    target = ["--device", "cpu"] if where == "embedded" else ["--connect", service.endpoint]
    result = CliRunner().invoke(
        app, ["bench", "load", "--sessions", "2", "--worlds", "4", "--rate", "10", "--seconds", "3", "--json", *target],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = json.loads(result.stdout)
    assert [r["session"] for r in rows] == [0, 1]
    for r in rows:
        assert r["sent"] >= 25 and r["estimates"] >= 0.8 * r["sent"], r
        assert 0 < r["latency_p50_ms"] <= r["latency_p99_ms"] and r["rss_mib_end"] > 0, r


def test_a_loop_that_stops_coming_round_takes_the_service_down_loudly(traj):
    """A robot streams while a new population's build holds the device for longer than this
    service's watchdog allows: the loop, waiting its turn, stops coming round; the watchdog
    withdraws the service's token and `serve` exits non-zero (a live token on a stuck loop would
    look healthy to every robot)."""
    # 1 s: the first open's small build (a device stage well under a second, even on a busy CI
    # machine) must pass; the second's, of 2048 worlds (a stage of 1.5 s or more on a CPU), not.
    svc = ServiceProcess(free_port(), watchdog_s="1.0")
    with TrackerClient(connect=[svc.endpoint]) as robot, TrackerClient(connect=[svc.endpoint]) as newcomer:
        svc.wait_ready(robot)
        robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=4)
        stop = threading.Event()

        def stream() -> None:
            n = 0
            while not stop.wait(0.05):
                robot.send(traj.frame(n % traj.frames, robot.info.session, seq=n))
                n += 1

        worker = threading.Thread(target=stream)
        worker.start()
        try:
            try:  # answered or not: the service is going down meanwhile
                newcomer.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=2048)
            except (TimeoutError, TrackerError):
                pass
            svc.proc.wait(timeout=30)  # promptly, though the build may still be running
        finally:
            stop.set()
            worker.join()
        log = svc.proc.stdout.read()
    assert svc.proc.returncode == 1 and "has not come round" in log and "withdrawing" in log, log[-2000:]


def test_an_open_that_builds_a_population_does_not_freeze_running_sessions(traj, caplog):
    """A robot streams at 10 Hz while another opens with a K that needs a population of its own:
    the build runs beside the loop, so the first robot's estimates keep coming through it; the
    newcomer waits for the build past its client's query timeout, is told it waited for it, and
    its client's log says the service was building while it waited."""
    svc = ServiceProcess(free_port(), groups=1)
    rate = 10.0
    try:
        newcomer = TrackerClient(connect=[svc.endpoint], timeout=1.0)  # the build outlasts its queries
        with TrackerClient(connect=[svc.endpoint]) as robot, newcomer:
            svc.wait_ready(robot)
            robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=4)
            arrivals: list[float] = []
            robot.on_pose(lambda est: arrivals.append(time.monotonic()))
            stop = threading.Event()

            def stream() -> None:
                n = 0
                t0 = time.perf_counter()
                while not stop.is_set():
                    time.sleep(max(0.0, t0 + n / rate - time.perf_counter()))
                    robot.send(traj.frame(n % traj.frames, robot.info.session, seq=n))
                    n += 1

            worker = threading.Thread(target=stream)
            worker.start()
            try:
                time.sleep(1.0)
                began = time.monotonic()
                with caplog.at_level(logging.INFO, logger="inhand_tracker.client"):
                    opened = newcomer.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=1024)
                ended = time.monotonic()
            finally:
                stop.set()
                worker.join()
            during = [t for t in arrivals if began <= t <= ended]
            gaps = np.diff([began, *during, ended])
            assert ended - began > 1.0, "the build was too quick to tell"
            assert "its population was built for it" in (opened.notice or ""), opened.notice
            assert newcomer.service_info().build_s > 1.0
            if ended - began > 4.0:  # the client's first look is 2 s into the wait
                assert "is building a population for this open" in caplog.text, caplog.text
            # On the CPU each device stage of the build (a frame of 1024 worlds) holds the loop for
            # up to a second; frames it holds up past max_frame_age_s are counted stale, not stepped.
            assert len(during) >= 3, (during, began, ended)
            assert gaps.max() < 0.6 * (ended - began), (gaps, ended - began)
    finally:
        svc.stop()


def test_a_tls_session_tracks_and_a_plain_peer_is_kept_out(traj, tmp_path):
    """TLS without client certificates: robots that trust the lab's CA track over it."""
    certs = _certificates(tmp_path)
    server = tmp_path / "server.json5"
    tls = {"listen_certificate": str(certs["router.crt"]), "listen_private_key": str(certs["router.key"])}
    server.write_text(json.dumps({"transport": {"link": {"tls": tls}}}))
    client = tmp_path / "client.json5"
    client.write_text(json.dumps({"transport": {"link": {"tls": {"root_ca_certificate": str(certs["ca.crt"])}}}}))
    svc = ServiceProcess(free_port(), scheme="tls", zenoh_config=str(server))
    try:
        with TrackerClient(connect=[svc.endpoint], zenoh_file=client) as robot:
            svc.wait_ready(robot)
            info = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=4)
            robot.send(traj.frame(0, info.session))
            assert robot.latest_pose(timeout=60, after_seq=0).seq == 0
        _kept_out(svc.endpoint.replace("tls/", "tcp/"))
    finally:
        svc.stop()


@contextlib.contextmanager
def _hardened(tmp_path: Path, **settings: str):
    """docker/compose-tls.yml's deployment from its Zenoh files as shipped, their certificate paths
    and port moved here: make-certs.sh's certificates for two robots ("robot", "observer") and its
    router.json5 with their access rules, a router running it, and the service as its client with
    the service's certificate. Yields the router's endpoint, a function that gives a shipped Zenoh
    file (``router.json5`` from the certificates' folder, the others from docker/tls) and the service."""
    certs = tmp_path / "certs"
    _certificates(certs)
    port = free_port()

    def shipped(name: str, robot: str = "robot") -> Path:
        text = (certs / name if name == "router.json5" else ROOT / "docker/tls" / name).read_text()
        text = text.replace("/certs/", f"{certs}/").replace('"certs/', f'"{certs}/').replace(":7447", f":{port}")
        path = tmp_path / f"{robot}-{name}"
        path.write_text(text.replace("certs/robot.", f"certs/{robot}."))
        return path

    router = subprocess.Popen(
        [sys.executable, "-c", "import sys, time, zenoh\n"
         "s = zenoh.open(zenoh.Config.from_file(sys.argv[1])); print('up', flush=True); time.sleep(3600)",
         shipped("router.json5")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    assert router.stdout.readline().strip() == "up"
    svc = ServiceProcess(0, listen=False, connect="", zenoh_config=str(shipped("service.json5")), **settings)
    try:
        yield f"tls/127.0.0.1:{port}", shipped, svc
    finally:
        svc.stop()
        router.kill()
        router.wait()


def test_under_the_hardened_router_a_robot_opens_and_reopens_while_another_floods(traj, tmp_path):
    """Behind the shipped router a second robot with a valid certificate may open only under its own
    name: its flood fills its own caps and is refused there, while the first robot, listed in the
    service's robot_keys, opens, closes and opens again."""
    from inhand_tracker.protocol.identity import RobotKey

    listed = RobotKey.load_or_create(tmp_path / "robot.key").fingerprint
    # The flood's sessions hold no liveliness token: a long robot timeout keeps them open meanwhile.
    caps = {"max_sessions_per_peer": "2", "robot_timeout_s": "60", "robot_keys": f'{{"robot": "{listed}"}}'}
    with _hardened(tmp_path, **caps) as (endpoint, shipped, svc):
        with TrackerClient(connect=[endpoint], zenoh_file=shipped("robot.json5", robot="observer")) as flood:
            svc.wait_ready(flood)
            answers = []
            for peer in ["observer"] * 4 + ["robot"] * 2:  # under its own name, then under the robot's
                payload = encode(_request(traj).model_copy(update={"worlds": 2}))
                wait = 60 if peer == "observer" else 3
                replies = list(flood._zenoh.get(Keys("default", peer).open, payload=payload, timeout=wait))
                answers.append("none" if not replies else "ok" if replies[0].ok is not None else "refused")
            assert answers == ["ok", "ok", "refused", "refused", "none", "none"], answers
        robot = TrackerClient(connect=[endpoint], zenoh_file=shipped("robot.json5"), peer="robot",
                              identity=tmp_path / "robot.key")  # fmt: skip
        with robot:
            info = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=2)
            assert info.session.startswith("robot~")
            robot.close_session()
            again = robot.reopen()
            robot.send(traj.frame(0, again.session))
            assert robot.latest_pose(timeout=60, after_seq=0).seq == 0


def test_the_hardened_compose_runs_the_service_and_robots_as_clients_of_an_mtls_router(traj, tmp_path):
    """A router that accepts only mTLS, the service as its client with no endpoint of its own, a
    robot with its certificate tracking through it, the health check through it, and a peer without
    a certificate kept out."""
    with _hardened(tmp_path) as (endpoint, shipped, svc):
        with TrackerClient(connect=[endpoint], zenoh_file=shipped("robot.json5"), peer="robot") as robot:
            svc.wait_ready(robot)
            info = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=4)
            robot.send(traj.frame(0, info.session))
            assert robot.latest_pose(timeout=60, after_seq=0).seq == 0
            env = os.environ | {"INHAND_ZENOH_CONFIG": str(tmp_path / "robot-service.json5")}
            health = subprocess.run([sys.executable, "-m", "inhand_tracker.client.health", endpoint], env=env, cwd=ROOT,
                                    capture_output=True, text=True, timeout=60)  # fmt: skip
            assert health.returncode == 0 and "healthy" in health.stdout, health.stderr
        stranger = tmp_path / "stranger.json5"
        stranger.write_text(json.dumps({"mode": "client", "transport": {"link": {"tls": {
            "root_ca_certificate": str(tmp_path / "certs" / "ca.crt")}}}}))  # fmt: skip
        with pytest.raises(zenoh.ZError, match="Unable to connect"):  # a client must reach the router
            TrackerClient(connect=[endpoint], zenoh_file=stranger)


def test_under_the_hardened_composes_access_rules_a_second_robot_can_neither_sniff_forge_nor_intercept(traj, tmp_path):
    """A second robot with a valid certificate of the same lab subscribes to every session's
    frames and observations, answers every service key in the service's place, publishes forged
    estimates on the first robot's key, puts frames on it, asks its status, tries to close its
    session and to open under its name, and holds a liveliness token on the service's key. The
    router's access rules (make-certs.sh's router.json5, each robot confined to its own sessions'
    keys) let none of it through: 0 frames sniffed, 0 queries caught, 0 forged estimates delivered,
    0 of its frames in the first robot's status, no status answered, the session still open, no
    open under another's name, the first robot keeps >= 95 %
    of its 10 Hz estimate rate meanwhile, and learns of the service's death when it dies."""
    with _hardened(tmp_path) as (endpoint, shipped, svc):
        attacker = zenoh.open(zenoh_config(connect=[endpoint], file=shipped("robot.json5", robot="observer")))
        keys, caught, sniffed = Keys("default"), [], []
        forged = []

        def answer(query: zenoh.Query) -> None:
            caught.append(str(query.key_expr))
            query.reply(query.key_expr, b"forged")

        remote = zenoh.Locality.REMOTE  # what it sends itself it would hear locally: not a leak
        held = [attacker.declare_subscriber(keys.every(kind), sniffed.append, allowed_origin=remote)
                for kind in ("frame", "observation")]  # fmt: skip
        held += [attacker.declare_queryable(k, answer, allowed_origin=remote)
                 for k in (keys.info, keys.opens, keys.close, keys.every("pose"), keys.every("status"))]  # fmt: skip
        held.append(attacker.liveliness().declare_token(keys.alive))
        try:
            with TrackerClient(connect=[endpoint], zenoh_file=shipped("robot.json5"), peer="robot") as robot:
                svc.wait_ready(robot)
                info = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=4)
                request = encode(_request(traj))
                assert list(attacker.get(Keys("default", "robot").open, payload=request, timeout=3)) == []
                assert list(attacker.get(keys.open, payload=request, timeout=3)) == []  # under no name
                (own,) = list(attacker.get(Keys("default", "observer").open, payload=request, timeout=60))
                assert own.ok is not None  # under its own name it may open
                got: list[int] = []
                robot.on_pose(lambda est: (got.append(est.seq), est.seq >= 10**6 and forged.append(est)))
                robot.send(traj.frame(0, info.session))
                first = robot.latest_pose(timeout=60, after_seq=0)
                fake = encode(first.model_copy(update={"seq": 10**6}))
                seconds, rate, sent = 4.0, 10.0, 0
                t0 = time.perf_counter()
                while time.perf_counter() - t0 < seconds:
                    time.sleep(max(0.0, t0 + sent / rate - time.perf_counter()))
                    sent += 1
                    robot.send(traj.frame(sent, info.session))
                    attacker.put(keys.pose(info.session), fake)
                    attacker.put(keys.frame(info.session), encode(traj.frame(sent, info.session, token="0" * 32)))
                time.sleep(1.0)
                guess = CloseSession(session=info.session, token="0" * 32)
                list(attacker.get(keys.close, payload=encode(guess), timeout=3))
                status = robot.status()
                assert status.frames >= sent  # still open: its status answers
                assert status.errors == 0, status.last_error  # the observer's frames never reached it
                ask = CloseSession(session=info.session, token="0" * 32)
                assert list(attacker.get(keys.status(info.session), payload=encode(ask), timeout=3)) == []
                answered = len([s for s in got if 0 < s <= sent])
                assert answered >= 0.95 * sent, (answered, sent)
                # The attacker holds a token on the service's liveliness key: the router never let
                # it through, so the service's death is the robot's news at once.
                svc.proc.kill()
                deadline = time.monotonic() + 5.0
                while not robot.service_lost and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert robot.service_lost
        finally:
            for h in held:
                h.undeclare()
            attacker.close()
        assert sniffed == [] and caught == [] and forged == [], (len(sniffed), caught, len(forged))


def test_a_silent_co_tenant_stops_costing_its_population_a_wait(traj):
    """A session that opened and sends nothing is waited for a few steps, then no more: the robot
    beside it steps as soon as its own frame arrives; once the silent one sends, it is awaited again."""
    from inhand_tracker.service.server.pools import SILENT_AFTER

    manager = _manager()
    robot, quiet = (manager.open(_request(traj)) for _ in range(2))
    pool = manager.sessions[robot.session].pool
    assert manager.sessions[quiet.session].pool is pool  # one population, two groups
    for seq in range(SILENT_AFTER + 2):
        manager.submit(traj.frame(seq, robot.session, token=robot.token))
        ready = manager.ready(max_wait=3600.0) == [pool]
        assert ready == (seq >= SILENT_AFTER), seq  # waited for while it may still speak, then not
        manager.step(pool)
    manager.submit(traj.frame(0, quiet.session, token=quiet.token))
    manager.step(pool)
    manager.submit(traj.frame(SILENT_AFTER + 2, robot.session, token=robot.token))
    assert manager.ready(max_wait=3600.0) == []  # it spoke: it is awaited again


def test_a_robot_that_knows_its_service_s_key_accepts_no_fake_service_relay_or_forged_estimate(traj, tmp_path):
    """The plain deployment (no access rules), a robot configured with the fingerprint `serve`
    prints: a peer answering as the service is refused; a peer that relays the robot's open to the
    real service gets a reply without the session's secret and cannot close the session; an
    estimate forged on the session's pose key is not taken; the genuine ones are."""
    from inhand_tracker.client.trust import Trust
    from inhand_tracker.protocol.identity import ServiceKey, signed

    svc = ServiceProcess(free_port(), timeout_s=5.0, key_file=str(tmp_path / "service.key"))
    try:
        with TrackerClient(connect=[svc.endpoint]) as probe:
            svc.wait_ready(probe)
            fingerprint = ServiceKey.load_or_create(tmp_path / "service.key").fingerprint
            info = probe.service_info()

        # A fake service: another key, its info signed with it (answering from the robot's own Zenoh
        # session, so that nothing but the fake can answer, whatever the routing).
        fake_key = ServiceKey.generate()
        fake = info.model_copy(update={"name": "fake", "key": fake_key.public})
        answer = encode(signed(fake_key, fake))
        with TrackerClient(connect=[svc.endpoint], service="fake", service_key=fingerprint) as robot:
            robot._zenoh.declare_queryable(Keys("fake").info, lambda q: q.reply(q.key_expr, answer))
            with pytest.raises(TrackerError, match="does not hold the key"):
                robot.service_info()

        with TrackerClient(connect=[svc.endpoint], service_key=fingerprint) as robot:
            opened = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q,
                                        worlds=4)  # fmt: skip
            assert opened.token and len(opened.token) == 32  # agreed, not sent
            # A relay that forwards an open a robot made (its key, its proof) gets no secret back,
            # and the same open sent again is refused.
            request = Trust(fingerprint).request(_request(traj), robot.service_info())
            (reply,) = list(robot._zenoh.get(Keys("default").open, payload=encode(request), timeout=60))
            relayed = decode(bytes(reply.ok.payload.to_bytes()), SessionInfo)
            assert relayed.token == "" and relayed.signature
            (reply,) = list(robot._zenoh.get(Keys("default").open, payload=encode(request), timeout=60))
            assert "(a replay)" in decode(bytes(reply.err.payload.to_bytes()), Error).message
            with pytest.raises(TrackerError, match="forbidden"):
                robot._get(Keys("default").close, CloseSession(session=opened.session, token=""), Error)
            for i in range(3):
                robot.send(traj.frame(i, opened.session))
            genuine = robot.latest_pose(timeout=60, after_seq=2)
            # A forged estimate on the session's pose key: a seq ahead, the robot's old MAC.
            forged = genuine.model_copy(update={"seq": 99, "pose": genuine.pose + 0.1})
            robot._zenoh.put(Keys("default").pose(opened.session), encode(forged))
            time.sleep(0.5)
            assert robot.trust.forged == 1 and robot.latest_pose(timeout=1).seq == 2
            robot.send(traj.frame(3, opened.session))
            assert robot.latest_pose(timeout=60, after_seq=3).seq == 3  # the service's are still taken
    finally:
        svc.stop()
    assert f"key {fingerprint}" in svc.proc.stdout.read()  # `serve` says what robots are configured with


def test_a_robot_that_knows_its_service_s_key_sees_its_death_through_a_foreign_alive_token(traj, tmp_path):
    """A peer holds a liveliness token on the service's ``alive`` key, so the token never goes
    away; the service is killed. A robot without the key keeps waiting; one with it misses the
    service's signed beats and raises ServiceLost within seconds."""
    from inhand_tracker.protocol.identity import ServiceKey

    svc = ServiceProcess(free_port(), timeout_s=5.0, key_file=str(tmp_path / "service.key"))
    try:
        with TrackerClient(connect=[svc.endpoint]) as probe:
            svc.wait_ready(probe)
        fingerprint = ServiceKey.load_or_create(tmp_path / "service.key").fingerprint
        with (
            zenoh.open(zenoh_config(connect=[svc.endpoint])) as impostor,
            TrackerClient(connect=[svc.endpoint], service_key=fingerprint) as keyed,
            TrackerClient(connect=[svc.endpoint]) as blind,
        ):
            token = impostor.liveliness().declare_token(Keys("default").alive)
            for robot in (keyed, blind):
                info = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q,
                                          worlds=4)  # fmt: skip
                robot.send(traj.frame(0, info.session))
                assert robot.latest_pose(timeout=60, after_seq=0).seq == 0
            svc.proc.kill()
            svc.proc.wait()
            began = time.monotonic()
            with pytest.raises(ServiceLost):
                keyed.latest_pose(timeout=10, after_seq=10**6)
            assert time.monotonic() - began < 5.0
            assert not blind.service_lost  # the impostor's token still stands for the dead service
            token.undeclare()
    finally:
        svc.stop()
