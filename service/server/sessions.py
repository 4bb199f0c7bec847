"""Tracking sessions: each is one group of a shared population, and all sessions of a population
step together in one graph replay per tick.

The manager is owned by one thread (the GPU loop); it knows nothing of Zenoh. ``open`` and
``close`` answer with messages or raise :class:`ServiceError` with a protocol error code;
frames go in with ``submit`` (seq order, gaps, duplicates and late frames counted), and ``tick``
steps every population that has work and returns the estimates to publish.
"""

from __future__ import annotations

import logging
import re
import secrets
import time
import uuid
from dataclasses import replace

import numpy as np

from inhand_tracker.protocol import (
    DEFAULT_WORLDS,
    CloseSession,
    ErrorCode,
    Estimate,
    OpenSession,
    PoseObservation,
    RobotFrame,
    SessionInfo,
    SessionStatus,
    Trajectory,
    sensing_field,
)
from inhand_tracker.protocol.auth import mac_of, verify, verify_query
from inhand_tracker.protocol.identity import ServiceKey, signed
from inhand_tracker.protocol.keys import session_id
from inhand_tracker.service.tracker import Frame, TrackerConfig
from inhand_tracker.sim_backend import ObjectSpec, RobotSpec, resolve_device
from inhand_tracker.sim_backend.kinematics import Kinematics

from .admission import Admission, Gate, ServiceError
from .budget import STEP_TIME_MOTION, FrameTimes, device_name, measure_step_times
from .config import ServiceConfig
from .frames import frame_problem, fresh, in_order
from .pools import MEASURED_STEPS, SILENT_AFTER, Pool, PoolKey, Session, Turn, build_pool, idle_pose
from .sources import Sources

__all__ = ["Admission", "ServiceError", "Session", "SessionManager"]

log = logging.getLogger(__name__)
_NOT_IN_A_TOKEN = re.compile(r"[^A-Za-z0-9_]")


def _token(text: str) -> str:
    """``text`` as a ROS name token: other characters as ``_``, a letter first."""
    token = _NOT_IN_A_TOKEN.sub("_", text)
    return token if token[:1].isalpha() else f"s_{token}"


_SAID = 500
"""The most characters of a refused input's error a session's status repeats."""


class SessionManager:
    """Every session and population of one service. One thread (the service's loop) owns it;
    only :meth:`build` may run on another, taking :attr:`turn` for its device work."""

    def __init__(
        self,
        config: ServiceConfig,
        robots: dict[str, RobotSpec],
        objects: dict[str, ObjectSpec],
        identity: ServiceKey | None = None,
    ):
        self.identity = identity or ServiceKey.generate()
        """The service's key: its replies' signatures, and each keyed open's secret."""
        self.device = resolve_device(config.device)
        # Unset, the layout and the rate suit the device: a GPU steps 8 sessions at about the cost
        # of one and keeps 30 Hz; a CPU pays for every session and world.
        cuda = self.device.is_cuda
        unset = {"groups": 8 if cuda else 1, "rate_hz": 30.0 if cuda else 10.0}
        config = config.model_copy(update={k: v for k, v in unset.items() if getattr(config, k) is None})
        self.config, self.robots, self.objects = config, robots, objects
        self.sessions: dict[str, Session] = {}
        self.pools: dict[PoolKey, Pool] = {}
        self.building: dict[PoolKey, int] = {}
        """Populations being built, by key, with the worlds each will hold."""
        self.turn = Turn()
        """Held for device work: the loop's steps and opens, and each device stage of a build."""
        self._built = 0
        """Populations built so far: a new one's key never repeats a dropped one's."""
        key = {"device": device_name(self.device), **config.physics.model_dump()}
        self.frame_times = FrameTimes.load(config.frame_time_cache, key)
        """p99 step time of a population by its worlds, on this device and physics setting."""
        self.gate = Gate(config, robots, objects, self.frame_times, self.pools, self.building, self.device)
        """The caps and the frame budget every open passes."""
        self.sources = Sources(config, self.identity)
        """Who opens: the robot keys proven, and the names they hold."""

    @property
    def budget_ms(self) -> float:
        """The p99 time all populations' steps may take together [ms]; inf without a budget."""
        return self.gate.budget_ms

    def load_ms(self) -> float:
        """The p99 step times of every population stepping or being built, summed [ms]."""
        return self.gate.load_ms()

    def free_worlds(self) -> int:
        """The most worlds (K) a session opened now in a new population would get; 0 when full."""
        return self.gate.free_worlds(len(self.sessions))

    # ------------------------------------------------------------------ open / close
    def open(self, request: OpenSession, peer: str = "") -> SessionInfo:
        """Open a session, building its population here if none has room (the service builds on
        another thread: :meth:`admit`, :meth:`build`, :meth:`adopt`, :meth:`attach`)."""
        admission = self.admit(request, peer)
        if admission.pool is None:
            self.gate.build_for(admission.source)
            self.reserve(admission)
            try:
                self.adopt(self.build(admission))
            finally:
                self.building.pop(admission.key, None)
            notice, admission = admission.notice, self.admit(admission.request, peer)
            admission.notice = admission.notice or notice
        return self.attach(admission)

    def admit(self, request: OpenSession, peer: str = "") -> Admission:
        """Validate an open under ``peer``'s name ("" for none; ServiceError naming the field and the
        numbers) and find its population: one with a free group, or none when one must be built."""
        self._check_name(request.name)
        source = self.sources.source(request, peer)
        return self.gate.admit(request, list(self.sessions.values()), peer, source)

    def _check_name(self, name: str | None) -> None:
        if name is not None and any(s.name == name for s in self.sessions.values()):
            raise ServiceError(ErrorCode.BAD_REQUEST, f"name: '{name}' is another open session's; choose another")

    def _name(self, request: OpenSession, peer: str, key: str = "") -> str:
        """The session's name: the one asked for, else its default (:attr:`OpenSession.name`), the same
        on every run and none another robot key holds. Where names are ROS 2 topics (``ros2``) a taken
        one is refused (a launch file could not name a topic numbered by open order), else numbered from 2."""
        if request.name is not None:
            self._check_name(request.name)  # taken while its population was built
            return request.name
        name = _token(f"{request.robot}_{request.object}")
        name = f"{_token(peer)}/{name}" if peer else name
        taken = {s.name for s in self.sessions.values()} | self.sources.held(key)
        if name in taken and self.config.ros2:
            raise ServiceError(
                ErrorCode.BAD_REQUEST,
                f"name: this session's default name '{name}' is another session's ROS 2 topic; give it a name of"
                " its own",
            )
        return next(n for n in (name, *(f"{name}_{i}" for i in range(2, len(taken) + 3))) if n not in taken)

    def reserve(self, admission: Admission) -> None:
        """Count a population being built against the caps until it is adopted (or failed)."""
        self.building[admission.key] = self.config.groups * admission.request.worlds

    def build(self, admission: Admission) -> Pool:
        """The population ``admission`` needs, with every group idle; safe on a thread of its own
        (it touches nothing of the manager's; its device work takes :attr:`turn`)."""
        request, cfg = admission.request, self.config
        obj = self.objects[request.object]
        return build_pool(admission.key, admission.robot, obj, admission.tracker_config, request.method,
                          cfg.groups, cfg.device, cfg.physics, self.turn)  # fmt: skip

    def adopt(self, pool: Pool) -> None:
        """Take a built population into service (its build no longer counts as one in flight)."""
        self.building.pop(pool.key, None)
        self._built += 1
        pool.key = replace(pool.key, serial=self._built)
        self.pools[pool.key] = pool

    def layout(self, robot: str):
        """The robot's layout (its joints, sensors and touch zones, in its frames' order)."""
        return self.gate.kinematics.setdefault(robot, Kinematics(self.robots[robot])).layout

    def attach(self, admission: Admission) -> SessionInfo:
        """Open the session in a free group of ``admission.pool``."""
        request, pool, source = admission.request, admission.pool, admission.source
        assert pool is not None, "attach: the admission has no population yet"
        layout = self.gate.kinematics[request.robot].layout
        q0 = layout.default_q if request.q0 is None else request.q0
        group = pool.sessions.index(None)
        sid = session_id(admission.peer, uuid.uuid4().hex[:12])
        # A keyed open's secret is agreed, never sent: a peer that relays the open learns nothing.
        keyed = bool(request.client_key)
        token = self.identity.session_secret(request.client_key, sid) if keyed else secrets.token_hex(16)
        name = self._name(request, admission.peer, source.key)
        self.sources.spend(request)
        session = Session(
            sid, token, request.robot, request.object, request.method, pool, group, name, admission.peer, source, keyed
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
        self.gate.opened(source)
        self.sources.bind(source, admission.peer, session.name)
        info = SessionInfo(
            session=session.id,
            token="" if keyed else session.token,
            robot=request.robot,
            object=request.object,
            joint_names=list(layout.joint_names),
            sensor_names=list(layout.sensor_names),
            zone_names=list(layout.zone_names),
            worlds=tracker.K,
            method=request.method,
            notice=admission.notice,
            name=session.name,
        )
        return signed(self.identity, info, request.client_key) if keyed else info

    def close(self, session_id: str, token: str) -> None:
        """Close a session at its robot's request (``token``: the session's secret)."""
        self.authorize(session_id, token)
        self.drop(session_id)

    def authorize_query(self, request: CloseSession, purpose: str) -> Session:
        """The session a ``purpose`` request ("status", "close") is about, if its robot sent it."""
        session = self.sessions.get(request.session)
        if session is None or not verify_query(request, session.token, purpose):
            raise ServiceError(ErrorCode.FORBIDDEN, f"session '{request.session}': not open, or not yours")
        if request.mac and not fresh(session, purpose, request.stamp, request.mac):
            raise ServiceError(ErrorCode.FORBIDDEN, f"session '{request.session}': {session.last_error}")
        return session

    def drop(self, session_id: str) -> None:
        """Close a session (if open); a population left without sessions is dropped, its memory and
        worlds freed."""
        session = self.sessions.get(session_id)
        if session is None:
            return
        pool = session.pool
        pool.sessions[session.group] = None
        del self.sessions[session_id]
        same = any(s.source.key == session.source.key and s.peer == session.peer for s in self.sessions.values())
        self.sources.closed(session.source.key, session.peer, session.name, same)
        if not pool.active:
            del self.pools[pool.key]

    def authorize(self, session_id: str, token: str) -> Session:
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
        traj = Trajectory.load(STEP_TIME_MOTION)
        replay = traj.robot in self.robots and traj.object in self.objects
        robot, obj = (traj.robot, traj.object) if replay else (next(iter(self.robots)), next(iter(self.objects)))
        cfg, cuda = self.config, self.device.is_cuda
        if not cfg.rate_hz:
            sizes = [DEFAULT_WORLDS if cuda else 1]
        else:
            sizes = [k for k in ((8, 128, 1024) if cuda else (1, 8)) if cfg.groups * k <= cfg.max_worlds]
        measure = cfg.rate_hz and any(cfg.groups * k not in self.frame_times.points for k in sizes)
        if not replay and measure:
            log.warning(
                "frame times: measuring with robot '%s' holding still (the bundled motion is the '%s' robot's);"
                " the populations' own steps will correct them", robot, traj.robot,
            )  # fmt: skip
        for k in sizes if measure else sizes[:1]:
            request = OpenSession(robot=robot, object=obj, p0=traj.truth.initial_pose, worlds=k)
            key, spec, shape = PoolKey(robot, obj, k), self.robots[robot], self.objects[obj]
            tracker = build_pool(key, spec, shape, TrackerConfig(), request.method, cfg.groups, cfg.device, cfg.physics,
                                 self.turn).tracker  # fmt: skip
            if measure:
                q0 = self.gate.kinematics.setdefault(robot, Kinematics(self.robots[robot])).layout.default_q
                ms = measure_step_times(tracker, traj if replay else None, q0, idle_pose(self.objects[obj]))
                self.frame_times.observe(tracker.G * tracker.K, ms, weight=1.0)
                log.info("frame times: %d worlds step in %.1f ms (p99) on %s", tracker.G * tracker.K, ms, self.device)
            del tracker
        if measure:
            self.frame_times.save(cfg.frame_time_cache)

    # ------------------------------------------------------------------ frames
    def submit(self, frame: RobotFrame, received: float | None = None) -> None:
        """Queue a frame in seq order; a duplicate or late one is dropped and counted, a gap counted;
        a frame of the wrong size or with values no robot sends (:func:`.frames.frame_problem`) is
        refused with the field and the numbers (and counted). A seq
        beyond the window either way re-synchronises the session to it; a full queue drops its oldest."""
        session = self.sessions.get(frame.session)
        if session is None or not verify(frame, session.token):
            if session is not None:  # its robot sees another peer publish
                session.errors += 1
                session.last_error = f"RobotFrame.mac: not the session's robot's (seq {frame.seq}); frame refused"
            raise ServiceError(ErrorCode.FORBIDDEN, f"session '{frame.session}': not open, or not yours")
        if session.failed is not None:
            session.errors += 1
            raise ServiceError(ErrorCode.INTERNAL, f"session '{session.id}' failed: {session.failed}; open a new one")
        if (problem := frame_problem(frame, session.pool.tracker.pop.layout)) is not None:
            session.errors += 1
            session.last_error = problem
            raise ServiceError(ErrorCode.BAD_REQUEST, problem)
        if not in_order(session, frame, self.config.seq_window, self.config.late_resync):
            return
        session.heard = time.monotonic()
        # The clock of the newest frame in seq order, not the largest ever seen: one frame stamped far
        # ahead must not make every later observation stale.
        session.newest_stamp = frame.stamp
        session.stamps.append(frame.stamp)
        if len(session.pending) >= self.config.max_pending:
            session.pending.popleft()
            session.stale += 1
        session.pending.append((frame, time.perf_counter() if received is None else received))

    def observe(self, observation: PoseObservation) -> None:
        """Queue a pose observation for the session's next step; one older than the newest frame by
        more than ``max_observation_age_s`` (robot clock) is counted stale and dropped."""
        session = self.sessions.get(observation.session)
        if session is None or not verify(observation, session.token):
            raise ServiceError(ErrorCode.FORBIDDEN, f"session '{observation.session}': not open, or not yours")
        if observation.mac and not fresh(session, "observation", observation.stamp, observation.mac):
            return
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

    def ready(self, max_wait: float) -> list[Pool]:
        """Populations to step now: every session it waits for has a frame, or the oldest has waited
        ``max_wait`` [s]. A session silent for :data:`.pools.SILENT_AFTER` steps is not waited for."""
        now = time.perf_counter()
        out = []
        for pool in self.pools.values():
            if pool.failed:
                continue
            waiting = [s.pending[0][1] for s in pool.active if s.pending]
            awaited = sum(1 for s in pool.active if s.pending or s.missed < SILENT_AFTER)
            if waiting and (len(waiting) >= awaited or now - min(waiting) >= max_wait):
                out.append(pool)
        return out

    def step(self, pool: Pool) -> list[Estimate]:
        """One tick of ``pool``: each session's next frame (others hold their last controls), one
        tracker step for all groups, an estimate for each session that sent a frame."""
        stepped: list[tuple[Session, RobotFrame, float]] = []
        oldest = time.perf_counter() - self.config.max_frame_age_s
        for s in pool.active:
            while len(s.pending) > 1 and s.pending[0][1] < oldest:  # overloaded: skip to what is fresh
                s.pending.popleft()
                s.stale += 1
            if not s.pending:
                s.missed += 1
                continue
            s.missed = 0
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
        if pool.steps % MEASURED_STEPS == 0:  # the device's curve learns from every population
            self.frame_times.observe(pool.worlds, self.gate.step_ms(pool))
        out = []
        joint_names, threshold = pool.tracker.pop.layout.joint_names, self.config.model_check
        for s, frame, received in stepped:
            g = s.group
            s.frames += 1
            latency = (done - received) * 1e3
            s.latencies.append(latency)
            if est.overflow is not None and est.overflow[g] and not s.overflow_said:
                s.overflow_said, cfg = True, pool.tracker.pop.config
                s.last_error = s.notice = (
                    f"contacts: worlds made more contacts than the {cfg.contacts_per_world} a world holds (or more"
                    f" than its {cfg.constraints_per_world} constraint rows) and dropped the excess: set the service's"
                    " [physics] contacts_per_world higher"
                )
            if est.joint_rms is not None and (said := s.check_model(est.joint_rms[g], joint_names, threshold)):
                log.warning("session %s (%s): %s", s.id, s.robot, said)
                s.notice = said
            s.latest = s.estimate(frame, est, latency)
            if s.keyed:  # its robot can tell the service's estimates from a forger's
                s.latest = s.latest.model_copy(update={"mac": mac_of(s.latest, s.token)})
            s.notice = None
            s.contacts_explored = bool(est.contacts_explored[g])
            out.append(s.latest)
        return out

    def fail(self, pool: Pool, reason: str) -> list[str]:
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

    def status(self, session_id: str, token: str) -> SessionStatus:  # a robot that sends its token
        return self.status_of(self.authorize(session_id, token))

    def status_of(self, s: Session) -> SessionStatus:
        return s.status(self.budget_ms if self.config.rate_hz else 0.0, self.load_ms())

    def count_error(self, session_id: str, message: str) -> None:
        """A frame for this session that could not even be decoded. The message is cut short: a
        decoder's words quote what it was sent, and a peer may send a megabyte."""
        s = self.sessions.get(session_id)
        if s is not None:
            s.errors += 1
            s.last_error = message if len(message) <= _SAID else message[: _SAID - 3] + "..."
