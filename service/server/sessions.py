"""Tracking sessions: each is one group of a shared population, and all sessions of a population
step together in one graph replay per tick.

The manager is owned by one thread (the GPU loop); it knows nothing of Zenoh. ``open`` and
``close`` answer with messages or raise :class:`ServiceError` with a protocol error code;
frames go in with ``submit`` (seq order, gaps, duplicates and late frames counted), and ``tick``
steps every population that has work and returns the estimates to publish.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
import uuid
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from protocol import (
    AUTO,
    DEFAULT_WORLDS,
    PRESENCE,
    SENSING,
    Error,
    ErrorCode,
    Estimate,
    OpenSession,
    PoseObservation,
    RobotFrame,
    SessionInfo,
    SessionStatus,
    TrackState,
    Trajectory,
    check_version,
    sensing_field,
)
from service.paths import DATA_DIR
from service.tracker import METHODS, Frame, OptimizerConfig, Tracker, TrackerConfig, setting_types
from sim_backend import ObjectSpec, Population, PopulationConfig, RobotSpec, resolve_device
from sim_backend.kinematics import Kinematics

from .budget import FrameTimes, affordable_worlds, device_name, ladder
from .config import ServiceConfig

__all__ = ["Admission", "ServiceError", "SessionManager"]

log = logging.getLogger(__name__)

_TUNABLE = setting_types(TrackerConfig)
"""Tracker hyperparameters a session may override, with their types."""


_CALIBRATION = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
"""What the frame times are calibrated on: a pick and place, the hand in contact for most of it."""
_MEASURED_STEPS = 100
"""A population's own p99 replaces the prediction for it once it stepped this often."""


class ServiceError(Exception):
    """A request the service refuses: a protocol error code and a message naming the numbers."""

    def __init__(self, code: ErrorCode, message: str):
        super().__init__(message)
        self.code, self.message = code, message

    def to_message(self, others: list[str] | None = None) -> Error:
        return Error(code=self.code, message=self.message, others=others or [])


@dataclass
class _Session:
    id: str
    token: str
    """The session's secret: frames, close, status and pose queries must carry it."""
    robot: str
    object: str
    method: str
    pool: _Pool
    group: int
    next_seq: int = 0
    pending: deque = field(default_factory=deque)
    """Accepted frames not yet stepped, in seq order: (frame, receive time)."""
    frames: int = 0
    gaps: int = 0
    duplicates: int = 0
    late: int = 0
    stale: int = 0
    resyncs: int = 0
    errors: int = 0
    last_error: str | None = None
    observations: int = 0
    observations_stale: int = 0
    reseeds_by_observation: int = 0
    observed: deque = field(default_factory=lambda: deque(maxlen=8))
    """Pose observations accepted and not yet applied (the newest few)."""
    newest_stamp: float | None = None
    """The robot clock of the newest frame accepted [s]."""
    latencies: deque = field(default_factory=lambda: deque(maxlen=1000))
    latest: Estimate | None = None
    contacts_explored: bool = False
    failed: str | None = None
    """Why the session's population failed; it takes no more frames then."""
    notice: str | None = None
    """Said to the robot with its next estimate, then cleared."""
    heard: float = field(default_factory=time.monotonic)
    """When the session last received a frame (or opened) [s, monotonic]."""


@dataclass
class _Pool:
    """One population (robot, object, K, tracker settings) with a fixed number of group slots."""

    key: tuple
    tracker: Tracker
    sessions: list[_Session | None]
    sensing: dict[str, np.ndarray]
    """What every group's robot last sent, each field of protocol.SENSING as (G, ...): a group
    without a frame this tick holds its last controls and joints (the start pose at first), and
    touch it did not send is zero."""
    present: dict[str, np.ndarray]
    """Which presence groups each group's robot sent in its last frame, {"force": (G,) bool, ...}."""

    failed: bool = False
    """Its step raised: it steps no more and takes no new sessions."""
    step_ms: deque = field(default_factory=lambda: deque(maxlen=3 * _MEASURED_STEPS))
    """Its latest steps' times [ms]."""
    steps: int = 0

    @property
    def active(self) -> list[_Session]:
        return [s for s in self.sessions if s is not None]

    @property
    def worlds(self) -> int:
        return self.tracker.G * self.tracker.K


class Turn:
    """A lock granted in the order it was asked for. ``threading.Lock`` is not fair: the loop,
    releasing and re-taking it every step, would keep a population build waiting for ever."""

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._next = self._serving = 0

    def __enter__(self) -> None:
        with self._changed:
            ticket, self._next = self._next, self._next + 1
            self._changed.wait_for(lambda: self._serving == ticket)

    def __exit__(self, *exc) -> None:
        with self._changed:
            self._serving += 1
            self._changed.notify_all()


@dataclass
class Admission:
    """A validated open: the request, the population it belongs in, and its settings."""

    request: OpenSession
    """As asked, but for ``worlds``: the K granted."""
    key: tuple
    """(robot, object, worlds, overrides): sessions with the same key share a population."""
    robot: RobotSpec
    tracker_config: TrackerConfig
    notice: str | None = None
    """Why fewer worlds were granted than asked for."""
    pool: _Pool | None = None
    """A population with a free group; None when one must be built first (or is being built:
    its key is in :attr:`SessionManager.building`)."""


class SessionManager:
    """Every session and population of one service. One thread (the service's loop) owns it;
    only :meth:`build` may run on another, taking :attr:`turn` for its device work."""

    def __init__(self, config: ServiceConfig, robots: dict[str, RobotSpec], objects: dict[str, ObjectSpec]):
        self.config, self.robots, self.objects = config, robots, objects
        self.device = resolve_device(config.device)
        self.sessions: dict[str, _Session] = {}
        self.pools: dict[tuple, _Pool] = {}
        self.building: dict[tuple, int] = {}
        """Populations being built, by key, with the worlds each will hold."""
        self.turn = Turn()
        """Held for device work: the loop's steps and opens, and each device stage of a build."""
        self._kinematics: dict[str, Kinematics] = {}
        self._opened: deque[float] = deque()
        """When sessions were opened in the last minute [s, monotonic]."""
        self._built = 0
        """Populations built so far: a new one's key never repeats a dropped one's."""
        budget = ("substeps", "iterations", "ls_iterations", "tolerance", "ls_tolerance")
        physics = {k: getattr(config, k) for k in budget}
        self.frame_times = FrameTimes.load(config.frame_time_cache, {"device": device_name(self.device), **physics})
        """p99 step time of a population by its worlds, on this device and physics setting."""

    # ------------------------------------------------------------------ the frame budget
    @property
    def budget_ms(self) -> float:
        """The p99 time all populations' steps may take together [ms]; inf without a budget."""
        cfg = self.config
        return 1e3 / cfg.rate_hz * cfg.budget_share if cfg.rate_hz else float("inf")

    def step_ms(self, pool: _Pool) -> float:
        """A population's p99 step time [ms]: its own once it stepped enough, else the prediction."""
        if len(pool.step_ms) >= _MEASURED_STEPS:
            return float(np.percentile(pool.step_ms, 99))
        return self.frame_times.predict(pool.worlds)

    def load_ms(self) -> float:
        """The p99 step times of every population stepping or being built, summed [ms]."""
        building = sum(self.frame_times.predict(w) for w in self.building.values())
        return sum(self.step_ms(p) for p in self.pools.values() if not p.failed) + building

    def free_worlds(self) -> int:
        """The most worlds (K) a session opened now in a new population would get; 0 when full."""
        cfg = self.config
        if len(self.sessions) >= cfg.max_sessions or len(self.pools) + len(self.building) >= cfg.max_populations:
            return 0
        room = (cfg.max_worlds - self._worlds_in_use()) // cfg.groups
        if not cfg.rate_hz:
            return min(DEFAULT_WORLDS, room) if room >= 1 else 0
        sizes = ladder(cfg.min_worlds, cfg.max_worlds)
        return affordable_worlds(self.frame_times, self.load_ms(), self.budget_ms, cfg.groups, sizes, room)

    def _worlds_in_use(self) -> int:
        return sum(p.worlds for p in self.pools.values()) + sum(self.building.values())

    def _grant(self, request: OpenSession, kind: tuple) -> tuple[int, str | None]:
        """The K an open gets, and why it is fewer than asked for (when it is): what was asked,
        if it fits the frame budget; a population of the same ``kind`` (robot, object,
        overrides) with a free group costs nothing more; else the most that fits, for "auto" or
        ``allow_fewer``; else a refusal naming the numbers."""
        cfg, asked = self.config, request.worlds
        if asked != AUTO and asked > cfg.max_worlds:
            raise ServiceError(ErrorCode.CAPACITY, f"worlds: {asked} exceeds this service's limit of {cfg.max_worlds}")
        if not cfg.rate_hz:
            return (DEFAULT_WORLDS if asked == AUTO else asked), None
        joinable = [k[2] for k, p in self.pools.items() if (k[0], k[1], k[3]) == kind and None in p.sessions]
        joinable += [k[2] for k in self.building if (k[0], k[1], k[3]) == kind]
        if asked != AUTO and asked in joinable:
            return asked, None
        load, budget, g = self.load_ms(), self.budget_ms, cfg.groups
        room = (cfg.max_worlds - self._worlds_in_use()) // g
        if asked != AUTO and asked <= room and load + self.frame_times.predict(g * asked) <= budget:
            return asked, None
        cap = room if asked == AUTO else min(asked, room)
        new = affordable_worlds(self.frame_times, load, budget, g, ladder(cfg.min_worlds, cfg.max_worlds), cap)
        best = max([new, *(k for k in joinable if k <= cap)])
        per = f"{cfg.rate_hz:g} Hz x {cfg.budget_share:g}"
        if asked == AUTO:
            if best:
                return best, None
            t = self.frame_times.predict(g * cfg.min_worlds)
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"worlds: no room in the frame budget of {budget:.1f} ms ({per}) on {self.device}: "
                f"{load:.1f} ms in use, and a population of {g} x {cfg.min_worlds} worlds (min_worlds) would "
                f"add about {t:.1f} ms (p99)",
            )
        t = self.frame_times.predict(g * asked)
        why = (
            f"a population of {g} x {asked} worlds would step in about {t:.1f} ms (p99) on {self.device}; "
            f"with {load:.1f} ms in use that passes the frame budget of {budget:.1f} ms ({per})"
        )
        if asked > room:
            why = f"{g} x {asked} worlds pass the service's limit of {cfg.max_worlds} ({g * room} free)"
        if request.allow_fewer and best >= cfg.min_worlds:
            return best, f"worlds: {asked} asked, {best} granted: {why}"
        fit = f"at most {best} fit now (allow_fewer to take them)" if best else "none fit now"
        raise ServiceError(ErrorCode.CAPACITY, f"worlds: {why}; {fit}")

    # ------------------------------------------------------------------ open / close
    def open(self, request: OpenSession) -> SessionInfo:
        """Open a session, building its population here if none has room (the service builds on
        another thread: :meth:`admit`, :meth:`build`, :meth:`adopt`, :meth:`attach`)."""
        admission = self.admit(request)
        if admission.pool is None:
            self.reserve(admission)
            try:
                self.adopt(self.build(admission))
            finally:
                self.building.pop(admission.key, None)
            notice, admission = admission.notice, self.admit(admission.request)
            admission.notice = admission.notice or notice
        return self.attach(admission)

    def admit(self, request: OpenSession) -> Admission:
        """Validate an open (ServiceError with the field and the numbers) and find its population:
        one with a free group, or none when one must be built or is on its way."""
        try:
            check_version(request.protocol)
        except ValueError as exc:
            raise ServiceError(ErrorCode.VERSION_MISMATCH, str(exc)) from None
        robot = self.robots.get(request.robot)
        if robot is None:
            raise ServiceError(ErrorCode.UNKNOWN_ROBOT, f"robot: '{request.robot}' is not one of {sorted(self.robots)}")
        if request.object not in self.objects:
            raise ServiceError(
                ErrorCode.UNKNOWN_OBJECT, f"object: '{request.object}' is not one of {sorted(self.objects)}"
            )
        if request.method not in METHODS:
            raise ServiceError(ErrorCode.BAD_REQUEST, f"method: expected one of {METHODS}, got '{request.method}'")
        if len(self.sessions) >= self.config.max_sessions:
            open_now, limit = len(self.sessions), self.config.max_sessions
            raise ServiceError(ErrorCode.CAPACITY, f"sessions: {open_now} open, this service's limit is {limit}")
        now = time.monotonic()
        while self._opened and now - self._opened[0] > 60.0:
            self._opened.popleft()
        if len(self._opened) >= self.config.max_opens_per_minute:
            limit = self.config.max_opens_per_minute
            raise ServiceError(
                ErrorCode.CAPACITY, f"opens: {len(self._opened)} in the last 60 s, this service's limit is {limit}"
            )
        unknown = sorted(set(request.overrides) - set(_TUNABLE))
        if unknown:
            raise ServiceError(ErrorCode.BAD_REQUEST, f"overrides: unknown {unknown} (tunable: {sorted(_TUNABLE)})")
        tconf = self._tracker_config(request)
        if request.robot not in self._kinematics:  # a model of its own: built once per robot
            self._kinematics[request.robot] = Kinematics(robot)
        d = self._kinematics[request.robot].layout.dof_count
        if request.q0 is not None and np.shape(request.q0) != (d,):
            got = np.shape(request.q0)[0]
            raise ServiceError(ErrorCode.BAD_REQUEST, f"q0: expected {d} joint positions, got {got}")
        overrides = tuple(sorted(request.overrides.items()))
        worlds, notice = self._grant(request, (request.robot, request.object, overrides))
        request = request.model_copy(update={"worlds": worlds})
        key = (request.robot, request.object, worlds, overrides)
        admission = Admission(request, key, robot, tconf, notice)
        for k, pool in self.pools.items():
            if k[:4] == key and None in pool.sessions and not pool.failed:
                admission.pool = pool
                return admission
        if key in self.building:
            return admission
        cfg = self.config
        populations = len(self.pools) + len(self.building)
        if populations >= cfg.max_populations:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"populations: {populations} built, this service's limit is {cfg.max_populations}"
                " (sessions share one when robot, object, worlds and overrides match)",
            )
        in_use = self._worlds_in_use()
        if in_use + cfg.groups * worlds > cfg.max_worlds:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"worlds: no room for {cfg.groups} x {worlds} more worlds ({in_use} in use, limit {cfg.max_worlds})",
            )
        return admission

    def reserve(self, admission: Admission) -> None:
        """Count a population being built against the caps until it is adopted (or failed)."""
        self.building[admission.key] = self.config.groups * admission.request.worlds

    def build(self, admission: Admission) -> _Pool:
        """The population ``admission`` needs, with every group idle; safe on a thread of its own
        (it touches nothing of the manager's; its device work takes :attr:`turn`)."""
        request, cfg = admission.request, self.config
        pop = Population(
            admission.robot,
            self.objects[request.object],
            PopulationConfig(
                groups=cfg.groups,
                worlds=request.worlds,
                device=cfg.device,
                substeps=cfg.substeps,
                iterations=cfg.iterations,
                ls_iterations=cfg.ls_iterations,
                tolerance=cfg.tolerance,
                ls_tolerance=cfg.ls_tolerance,
            ),
            turn=self.turn,
        )
        with self.turn:
            tracker = Tracker(pop, admission.tracker_config, methods=[request.method] * cfg.groups)
            g = pop.G
            sensing = {f.name: np.zeros((g, *f.shape(pop.D, pop.L)), np.float32) for f in SENSING}
            for f in SENSING:
                if f.per == "joint":
                    sensing[f.name][:] = pop.layout.default_q
            present = {p: np.zeros(g, bool) for p in PRESENCE}
            # Idle groups: the object rests on the table out of the hand's reach, where nothing happens.
            rest = -float(self.objects[request.object].mesh.bounds[0, 2])
            idle = np.tile(np.array([0.3, 0.0, rest, 0, 0, 0, 1], np.float32), (g, 1))
            tracker.start(idle, sensing["q"])
            tracker.capture()  # here, not in the loop's first step of it
            tracker.start(idle, sensing["q"])
        return _Pool(admission.key, tracker, [None] * g, sensing, present)

    def adopt(self, pool: _Pool) -> None:
        """Take a built population into service (its build no longer counts as one in flight)."""
        self.building.pop(pool.key, None)
        self._built += 1
        pool.key = (*pool.key, self._built)
        self.pools[pool.key] = pool

    def attach(self, admission: Admission) -> SessionInfo:
        """Open the session in a free group of ``admission.pool``."""
        request, pool = admission.request, admission.pool
        assert pool is not None, "attach: the admission has no population yet"
        kin = self._kinematics[request.robot]
        q0 = kin.layout.default_q if request.q0 is None else request.q0
        group = pool.sessions.index(None)
        session = _Session(
            uuid.uuid4().hex[:12], secrets.token_hex(16), request.robot, request.object, request.method, pool, group
        )
        tracker = pool.tracker
        tracker.set_method(group, request.method)
        mask = np.zeros(tracker.G, bool)
        mask[group] = True
        p0 = np.tile(np.array([0, 0, 0, 0, 0, 0, 1], np.float32), (tracker.G, 1))  # other groups: untouched
        p0[group] = request.p0
        p0[group, 3:] /= np.linalg.norm(request.p0[3:])
        for name, v in pool.sensing.items():
            v[group] = q0 if sensing_field(name).per == "joint" else 0.0
        for v in pool.present.values():
            v[group] = False
        with self.turn:
            tracker.start(p0, pool.sensing["q"], sigma_t=request.sigma_t, sigma_r=request.sigma_r, groups=mask)
        # Registered only now: an open that failed on the way leaves nothing behind.
        pool.sessions[group] = session
        self.sessions[session.id] = session
        self._opened.append(time.monotonic())
        return SessionInfo(
            session=session.id,
            token=session.token,
            robot=request.robot,
            object=request.object,
            joint_names=list(kin.layout.joint_names),
            sensor_names=list(kin.layout.sensor_names),
            worlds=tracker.K,
            method=request.method,
            notice=admission.notice,
        )

    @staticmethod
    def _tracker_config(request: OpenSession) -> TrackerConfig:
        """The session's tracker settings, refused with the field and the numbers before anything is built."""
        try:
            overrides = {k: _TUNABLE[k](v) for k, v in request.overrides.items()}
            return TrackerConfig(optimizer=OptimizerConfig(method=request.method), **overrides)
        except (ValueError, TypeError, OverflowError) as exc:
            raise ServiceError(ErrorCode.BAD_REQUEST, f"overrides: {exc}") from None

    def close(self, session_id: str, token: str) -> None:
        """Close a session at its robot's request (``token``: the session's secret)."""
        self.authorize(session_id, token)
        self.drop(session_id)

    def drop(self, session_id: str) -> None:
        """Close a session (if open); a population left without sessions is dropped, its memory and
        worlds freed."""
        session = self.sessions.get(session_id)
        if session is None:
            return
        pool = session.pool
        pool.sessions[session.group] = None
        del self.sessions[session_id]
        if not pool.active:
            del self.pools[pool.key]

    def authorize(self, session_id: str, token: str) -> _Session:
        """The session, if ``token`` is its secret; else FORBIDDEN (an unknown id answers the same,
        so a wrong token tells a peer nothing about which sessions exist)."""
        session = self.sessions.get(session_id)
        if session is None or not secrets.compare_digest(session.token, token):
            raise ServiceError(ErrorCode.FORBIDDEN, f"session '{session_id}': not open, or not yours (token)")
        return session

    def warm(self) -> None:
        """Compile the kernels before any robot waits on an open (minutes on a cold cache), and,
        with a frame budget, measure the step time at a few population sizes unless this device's
        are cached. One world per group on the CPU without a budget; the sizes ``auto`` grants
        first on CUDA, where some of Newton's kernels are compiled per size."""
        traj = Trajectory.load(_CALIBRATION)
        replay = traj.robot in self.robots and traj.object in self.objects
        robot, obj = (traj.robot, traj.object) if replay else (next(iter(self.robots)), next(iter(self.objects)))
        kin = self._kinematics.setdefault(robot, Kinematics(self.robots[robot]))
        cfg, cuda = self.config, self.device.is_cuda
        if not cfg.rate_hz:
            sizes = [DEFAULT_WORLDS if cuda else 1]
        else:
            sizes = [k for k in ((8, 128, 1024) if cuda else (1, 8)) if cfg.groups * k <= cfg.max_worlds]
        measure = cfg.rate_hz and any(cfg.groups * k not in self.frame_times.points for k in sizes)
        if not replay and measure:
            log.warning(
                "frame times: calibrating with robot '%s' holding still (the bundled motion is the '%s' robot's);"
                " the populations' own steps will correct them", robot, traj.robot,
            )  # fmt: skip
        for k in sizes if measure else sizes[:1]:
            request = OpenSession(robot=robot, object=obj, p0=traj.truth.initial_pose, worlds=k)
            tracker = self.build(Admission(request, (robot, obj, k, ()), self.robots[robot], TrackerConfig())).tracker
            if measure:
                rest = np.array([0.3, 0.0, -float(self.objects[obj].mesh.bounds[0, 2]), 0, 0, 0, 1], np.float32)
                ms = self._time_steps(tracker, traj if replay else None, kin.layout.default_q, rest)
                self.frame_times.observe(tracker.G * tracker.K, ms, weight=1.0)
                log.info("frame times: %d worlds step in %.1f ms (p99) on %s", tracker.G * tracker.K, ms, self.device)
            del tracker
        if measure:
            self.frame_times.save(cfg.frame_time_cache)

    @staticmethod
    def _time_steps(
        tracker: Tracker, traj: Trajectory | None, q0: np.ndarray, rest: np.ndarray, frames: int = 120
    ) -> float:
        """The p99 of a tracker's steps [ms] over ``frames`` of ``traj`` replayed in every group (the
        first third untimed: the hand reaches the object), or, without one, holding ``q0`` with the
        object at ``rest``."""
        g = tracker.G
        tile = lambda a: np.repeat(np.asarray(a, np.float32)[None], g, axis=0)  # noqa: E731
        if traj is None:
            pose = rest
            sensing = [{"controls": tile(q0), "q": tile(q0)}] * frames
        else:
            pose, frames = traj.truth.initial_pose, min(frames, traj.frames)
            sensing = [{n: tile(v[f]) for n, v in traj.sensing.items() if v is not None} for f in range(frames)]
        tracker.start(tile(pose), sensing[0]["q"])
        times = []
        for fields in sensing:
            began = time.perf_counter()
            tracker.step(Frame(**fields))
            times.append((time.perf_counter() - began) * 1e3)
        return float(np.percentile(times[frames // 3 :], 99))

    # ------------------------------------------------------------------ frames
    def submit(self, frame: RobotFrame, received: float | None = None) -> None:
        """Queue a frame in seq order; a duplicate or late one is dropped and counted, a gap counted;
        a frame of the wrong size is refused with the field and the numbers (and counted). A seq
        beyond the window either way re-synchronises the session to it; a full queue drops its oldest."""
        try:
            session = self.authorize(frame.session, frame.token)
        except ServiceError:
            if (known := self.sessions.get(frame.session)) is not None:  # its robot sees another peer publish
                known.errors += 1
                known.last_error = f"RobotFrame.token: does not match the session's (seq {frame.seq}); frame refused"
            raise
        if session.failed is not None:
            session.errors += 1
            raise ServiceError(ErrorCode.INTERNAL, f"session '{session.id}' failed: {session.failed}; open a new one")
        tracker = session.pool.tracker
        for f in SENSING:
            value, shape = getattr(frame, f.name), f.shape(tracker.D, tracker.L)
            if value is not None and value.shape != shape:
                session.errors += 1
                session.last_error = f"RobotFrame.{f.name}: expected shape {shape}, got {value.shape} (seq {frame.seq})"
                raise ServiceError(ErrorCode.BAD_REQUEST, session.last_error)
        last = session.pending[-1][0].seq if session.pending else session.next_seq - 1
        window = self.config.seq_window
        if abs(frame.seq - last) > window:
            session.resyncs += 1
            session.stale += len(session.pending)
            session.pending.clear()
            session.last_error = (
                f"RobotFrame.seq: jumped from {last} to {frame.seq}, beyond the service's window of {window}:"
                " re-synchronised to it"
            )
            session.notice = session.last_error
            session.next_seq = frame.seq
            last = frame.seq - 1
        if frame.seq <= last:
            if frame.seq == last:
                session.duplicates += 1
            else:
                session.late += 1
            return
        session.heard = time.monotonic()
        session.newest_stamp = max(frame.stamp, session.newest_stamp or frame.stamp)
        session.gaps += frame.seq - last - 1
        if len(session.pending) >= self.config.max_pending:
            session.pending.popleft()
            session.stale += 1
        session.pending.append((frame, time.perf_counter() if received is None else received))

    def observe(self, observation: PoseObservation) -> None:
        """Queue a pose observation for the session's next step; one older than the newest frame by
        more than ``max_observation_age_s`` (robot clock) is counted stale and dropped."""
        session = self.authorize(observation.session, observation.token)
        if session.failed is not None:
            raise ServiceError(ErrorCode.INTERNAL, f"session '{session.id}' failed: {session.failed}; open a new one")
        limit = self.config.max_observation_age_s
        if session.newest_stamp is not None and session.newest_stamp - observation.stamp > limit:
            session.observations_stale += 1
            session.last_error = (
                f"PoseObservation.stamp: {observation.stamp:.3f} s is {session.newest_stamp - observation.stamp:.3f} s"
                f" older than the newest frame ({session.newest_stamp:.3f} s), the limit is {limit} s: dropped"
            )
            return
        session.observed.append(observation)

    def ready(self, max_wait: float) -> list[_Pool]:
        """Populations to step now: every session has a frame, or the oldest has waited ``max_wait`` [s]."""
        now = time.perf_counter()
        out = []
        for pool in self.pools.values():
            if pool.failed:
                continue
            active = pool.active
            waiting = [s.pending[0][1] for s in active if s.pending]
            if waiting and (len(waiting) == len(active) or now - min(waiting) >= max_wait):
                out.append(pool)
        return out

    def step(self, pool: _Pool) -> list[Estimate]:
        """One tick of ``pool``: each session's next frame (others hold their last controls), one
        tracker step for all groups, an estimate for each session that sent a frame."""
        stepped: list[tuple[_Session, RobotFrame, float]] = []
        oldest = time.perf_counter() - self.config.max_frame_age_s
        for s in pool.active:
            while len(s.pending) > 1 and s.pending[0][1] < oldest:  # overloaded: skip to what is fresh
                s.pending.popleft()
                s.stale += 1
            if not s.pending:
                continue
            frame, received = s.pending.popleft()
            g = s.group
            for name, v in pool.sensing.items():
                value = getattr(frame, name)
                v[g] = 0.0 if value is None else value
            for name, v in pool.present.items():
                v[g] = getattr(frame, name) is not None
            s.next_seq = frame.seq + 1
            stepped.append((s, frame, received))
        with self.turn:
            began = time.perf_counter()
            est = pool.tracker.step(Frame(present=pool.present, **pool.sensing))
            done = time.perf_counter()
            for s in pool.active:
                while s.observed:  # scored against the worlds as they stand after this frame
                    seen = s.observed.popleft()
                    s.reseeds_by_observation += pool.tracker.observe(s.group, seen.pose, seen.covariance)
                    s.observations += 1
        pool.step_ms.append((done - began) * 1e3)
        pool.steps += 1
        if pool.steps % _MEASURED_STEPS == 0:  # the device's curve learns from every population
            self.frame_times.observe(pool.worlds, self.step_ms(pool))
        out = []
        for s, frame, received in stepped:
            g = s.group
            s.frames += 1
            latency = (done - received) * 1e3
            s.latencies.append(latency)
            s.latest = Estimate(
                session=s.id,
                seq=frame.seq,
                stamp=frame.stamp,
                pose=est.pose[g],
                mean_pose=est.mean_pose[g],
                covariance=est.covariance[g],
                cost=float(est.cost[g]),
                mass=float(est.mass[g]),
                friction=float(est.friction[g]),
                status=TrackState(int(est.status[g])).name.lower(),
                modes=est.modes[g],
                mode_weights=est.mode_weights[g],
                latency_ms=latency,
                notice=s.notice,
            )
            s.notice = None
            s.contacts_explored = bool(est.contacts_explored[g])
            out.append(s.latest)
        return out

    def fail(self, pool: _Pool, reason: str) -> list[str]:
        """Fail every session of ``pool`` with ``reason`` after its step raised: their queued frames
        are dropped and counted as errors, their status says why, and the population steps no more
        (it may hold half a frame). Returns the sessions' ids."""
        failed = []
        for s in pool.active:
            s.failed = reason
            s.errors += len(s.pending)
            s.pending.clear()
            s.last_error = f"internal: the session's population failed: {reason}"
            failed.append(s.id)
        pool.failed = True
        return failed

    def status(self, session_id: str, token: str) -> SessionStatus:
        s = self.authorize(session_id, token)
        lat = np.asarray(s.latencies) if s.latencies else np.zeros(1)
        cov = s.latest.covariance if s.latest is not None else np.zeros((6, 6))
        return SessionStatus(
            session=s.id,
            frames=s.frames,
            gaps=s.gaps,
            duplicates=s.duplicates,
            late=s.late,
            stale=s.stale,
            resyncs=s.resyncs,
            errors=s.errors,
            latency_p50_ms=float(np.percentile(lat, 50)),
            latency_p99_ms=float(np.percentile(lat, 99)),
            cost=float(s.latest.cost) if s.latest else 0.0,
            spread_m=float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))),
            last_error=s.last_error,
            observations=s.observations,
            observations_stale=s.observations_stale,
            reseeds_by_observation=s.reseeds_by_observation,
            budget_ms=self.budget_ms if self.config.rate_hz else 0.0,
            load_ms=self.load_ms(),
            contacts_explored=s.contacts_explored,
        )

    def count_error(self, session_id: str, message: str) -> None:
        """A frame for this session that could not even be decoded."""
        s = self.sessions.get(session_id)
        if s is not None:
            s.errors += 1
            s.last_error = message
