"""The frame budget: a step's time learnt per device, sessions sized to what still keeps up with
the robots, opens that would not refused (or shrunk) with the numbers, and robots spread over
several services behind one router."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import zenoh
from service_process import ServiceProcess, free_port

from inhand_tracker.client import TrackerClient, TrackerError, zenoh_config
from inhand_tracker.protocol import ErrorCode, OpenSession, Trajectory
from inhand_tracker.service.paths import DATA_DIR
from inhand_tracker.service.server.budget import FrameTimes, affordable_worlds, ladder
from inhand_tracker.service.server.config import ServiceConfig
from inhand_tracker.service.server.sessions import ServiceError, SessionManager
from inhand_tracker.sim_backend import load_catalog, load_robot

ROOT = Path(__file__).resolve().parents[1]
TRAJECTORY = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"


@pytest.fixture(scope="module")
def traj() -> Trajectory:
    return Trajectory.load(TRAJECTORY)


def test_the_step_time_curve_is_flat_below_linear_between_and_extrapolated_above():
    times = FrameTimes({"device": "x"}, {64: 5.0, 1024: 8.0, 4096: 20.0})
    assert times.predict(8) == 5.0  # a GPU's launch cost does not shrink with fewer worlds
    assert times.predict(2560) == pytest.approx(14.0)
    assert times.predict(8192) == pytest.approx(40.0)  # proportional growth past the largest: 20 x 2
    # A busy machine timed 64 worlds faster than 8: more worlds never cost less, and 4096 are
    # predicted at least in proportion, not at the cost of 64.
    busy = FrameTimes({}, {8: 20.0, 64: 10.0})
    assert busy.predict(64) == 20.0 and busy.predict(4096) == pytest.approx(20.0 * 4096 / 64)
    sizes = [1, 8, 16, 64, 256, 4096, 65536]
    assert all(np.diff([busy.predict(s) for s in sizes]) >= 0) and all(np.diff([times.predict(s) for s in sizes]) >= 0)
    assert FrameTimes({}, {10: 4.0}).predict(40) == pytest.approx(16.0)  # one point: through the origin
    assert FrameTimes({}).predict(1000) == 0.0
    times.observe(1024, 16.0)  # a quarter of the way: one busy second does not swing admission
    assert times.points[1024] == pytest.approx(10.0)
    assert ladder(8, 100) == [8, 16, 32, 64]
    assert affordable_worlds(times, 10.0, 26.0, 8, ladder(8, 65536), 65536) == 256  # 8 x 256: 13.3 ms
    assert affordable_worlds(times, 30.0, 26.0, 8, ladder(8, 65536), 65536) == 0


def test_frame_times_are_cached_per_device_and_settings(tmp_path):
    key = {"device": "NVIDIA H100", "substeps": 8}
    times = FrameTimes(key, {320: 7.5})
    times.save(tmp_path)
    assert FrameTimes.load(tmp_path, key).points == {320: 7.5}
    assert FrameTimes.load(tmp_path, {**key, "substeps": 6}).points == {}  # another setting: measured anew
    FrameTimes.path(tmp_path, key).write_text("{not json")
    assert FrameTimes.load(tmp_path, key).points == {}  # a broken cache is a cold start, not a crash


def _manager(tmp_path, **settings) -> SessionManager:
    robot = load_robot(ROOT / "configs/robots/allegro.toml")
    config = ServiceConfig(device="cpu", groups=1, frame_time_cache=str(tmp_path), **settings)
    return SessionManager(config, {robot.name: robot}, load_catalog())


def test_admission_refuses_or_shrinks_an_open_that_would_overrun_the_budget(traj, tmp_path):
    manager = _manager(tmp_path, rate_hz=10, min_worlds=4)  # 80 ms a frame
    manager.frame_times.points = {1: 5.0, 64: 40.0}
    request = OpenSession(robot=traj.robot, object=traj.object, p0=traj.truth.initial_pose, q0=traj.truth.initial_q)
    a = manager.open(request.model_copy(update={"worlds": 4}))
    pool = manager.sessions[a.session].pool
    load = manager.load_ms()
    assert load == pytest.approx(5.0 + 3 * 35 / 63)

    with pytest.raises(ServiceError) as exc:
        manager.open(request.model_copy(update={"worlds": 128}))
    message = exc.value.message
    assert exc.value.code == ErrorCode.CAPACITY
    assert "a population of 1 x 128 worlds would step in about 80.0 ms (p99) on cpu" in message, message  # 40 ms x 2
    assert f"with {load:.1f} ms in use" in message and "frame budget of 80.0 ms (10 Hz x 0.8)" in message, message
    assert "at most 64 fit now (allow_fewer to take them)" in message, message

    b = manager.open(request.model_copy(update={"worlds": 128, "allow_fewer": True}))
    assert b.worlds == 64 and b.notice.startswith("worlds: 128 asked, 64 granted"), b.notice
    # "auto": the largest power of two that still fits (40 + 22.2 + 6.7 ms; then + 8.9 ms), then none.
    assert [manager.open(request).worlds for _ in range(2)] == [32, 8]
    with pytest.raises(ServiceError, match=r"no room in the frame budget of 80\.0 ms .* 1 x 4 worlds"):
        manager.open(request)
    # The session already open was not touched: same population, same worlds, and it tracks.
    assert manager.sessions[a.session].pool is pool and pool.tracker.K == 4
    manager.submit(traj.frame(0, a.session, token=a.token))
    (estimate,) = manager.step(pool)
    assert estimate.session == a.session and estimate.seq == 0

    manager.close(b.session, b.token)  # its time goes back to the budget
    assert manager.open(request).worlds == 64


def test_a_service_calibrates_its_budget_and_refuses_or_shrinks_over_zenoh(traj, tmp_path):
    svc = ServiceProcess(free_port(), rate_hz="5", min_worlds="1", frame_time_cache=str(tmp_path))
    try:
        with TrackerClient(connect=[svc.endpoint]) as robot, TrackerClient(connect=[svc.endpoint]) as other:
            svc.wait_ready(robot)
            info = robot.service_info()
            assert (info.rate_hz, info.budget_ms, info.load_ms) == (5.0, 160.0, 0.0) and info.free_worlds >= 1
            (cache,) = tmp_path.glob("frame-times-*.json")  # measured on start-up, kept for the next
            assert set(json.loads(cache.read_text())["points"]) == {"1", "8"}

            opened = robot.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q,
                                        worlds=1)  # fmt: skip
            for i in range(5):
                robot.send(traj.frame(i, opened.session))
            assert robot.latest_pose(timeout=60, after_seq=4).seq == 4

            with pytest.raises(TrackerError) as exc:
                other.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=4096)
            assert exc.value.code == ErrorCode.CAPACITY
            numbers = re.search(
                r"1 x 4096 worlds would step in about ([\d.]+) ms .* budget of 160\.0 ms", str(exc.value)
            )
            assert numbers and float(numbers.group(1)) > 160, exc.value
            granted = other.open_session(
                traj.robot, traj.object, traj.truth.initial_pose, worlds=4096, allow_fewer=True
            )
            assert 1 <= granted.worlds < 4096 and "4096 asked" in granted.notice, granted

            for i in range(5, 10):  # the first robot goes on as before
                robot.send(traj.frame(i, opened.session))
            assert robot.latest_pose(timeout=60, after_seq=9).seq == 9
            status = robot.status()
            assert (status.frames, status.errors, status.budget_ms) == (10, 0, 160.0) and status.load_ms > 0
    finally:
        svc.stop()


def test_opens_without_a_service_name_go_where_there_is_room_behind_one_router(traj):
    """Two services (one per GPU, say) as clients of one router; each takes one session."""
    port = free_port()
    router_endpoint = f"tcp/127.0.0.1:{port}"
    conf = zenoh_config(listen=[router_endpoint])
    conf.insert_json5("mode", '"router"')
    services = []
    with zenoh.open(conf):
        try:
            for name in ("gpu-a", "gpu-b"):
                services.append(
                    ServiceProcess(free_port(), listen=False, name=name, connect=router_endpoint, max_sessions="1")
                )
            robots = [TrackerClient(connect=[router_endpoint], service=None) for _ in range(3)]
            for svc, name in zip(services, ("gpu-a", "gpu-b"), strict=True):
                with TrackerClient(connect=[router_endpoint], service=name) as probe:
                    svc.wait_ready(probe)
            opened = [
                r.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=2)
                for r in robots[:2]
            ]
            assert sorted(r.keys.service for r in robots[:2]) == ["gpu-a", "gpu-b"]
            for r, info in zip(robots[:2], opened, strict=True):
                r.send(traj.frame(0, info.session))
                assert r.latest_pose(timeout=60, after_seq=0).seq == 0
            with pytest.raises(TrackerError) as exc:  # both full
                robots[2].open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=2)
            assert exc.value.code == ErrorCode.CAPACITY
            with TrackerClient(connect=[router_endpoint], service="gpu-a") as named, pytest.raises(TrackerError) as exc:
                named.open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=2)
            assert exc.value.code == ErrorCode.CAPACITY and exc.value.others == ["gpu-b"], exc.value
            robots[1].close_session()
            free = robots[1].keys.service
            info = robots[2].open_session(traj.robot, traj.object, traj.truth.initial_pose, worlds=2)
            assert robots[2].keys.service == free and info.worlds == 2
            for r in robots:
                r.close()
        finally:
            for svc in services:
                svc.stop()
    assert np.all([svc.proc.returncode == 0 for svc in services])


def test_auto_grants_the_same_worlds_over_restarts_whose_step_times_moved_a_little(tmp_path):
    """Three starts of an idle service, each re-measuring its step times a few per cent apart around
    the budget's edge: the same K each time (it is kept in the cache); a real change moves it."""
    key, budget, sizes, kind = {"device": "cpu"}, 80.0, ladder(8, 1024), "('allegro', 'foam_brick', ())"
    granted = []
    for scale in (0.98, 1.04, 0.99):  # 32 worlds step in 78.4, 83.2, 79.2 ms against 80
        times = FrameTimes.load(tmp_path, key)
        times.points = {8: 20.0 * scale, 32: 80.0 * scale, 64: 160.0 * scale}
        granted.append(affordable_worlds(times, 0.0, budget, 1, sizes, 1024, times.granted.get(kind)))
        times.granted[kind] = granted[-1]
        times.save(tmp_path)
    assert granted == [32, 32, 32]
    times = FrameTimes.load(tmp_path, key)
    times.points = {8: 20.0, 32: 100.0, 64: 200.0}  # a quarter slower: 16 now
    assert affordable_worlds(times, 0.0, budget, 1, sizes, 1024, times.granted[kind]) == 16
    # Beside other populations the K is what fits, whatever was granted before.
    times.points = {8: 20.0, 32: 78.0, 64: 160.0}
    assert affordable_worlds(times, 10.0, budget, 1, sizes, 1024, 32) == 16
