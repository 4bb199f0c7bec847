"""Admission: which opens the service takes, and with how many worlds. An open is validated at
the boundary (each refusal names the field and the numbers), checked against the caps, and granted
the K that keeps every population's p99 step inside the frame budget."""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from inhand_tracker.protocol import AUTO, DEFAULT_WORLDS, Error, ErrorCode, OpenSession, check_version
from inhand_tracker.service.tracker import METHODS, OptimizerConfig, TrackerConfig
from inhand_tracker.service.tracker.settings import registry, tracker_config
from inhand_tracker.sim_backend import ObjectSpec, RobotSpec
from inhand_tracker.sim_backend.kinematics import Kinematics

from .budget import FrameTimes, affordable_worlds, ladder
from .config import ServiceConfig
from .pools import MEASURED_STEPS, Pool, PoolKey

__all__ = ["Admission", "Gate", "ServiceError"]

log = logging.getLogger(__name__)

_TUNABLE = sorted(name for name, s in registry().items() if s.session and s.kind is not str)
"""What a session's overrides may change, by dotted name (numbers and flags: the wire carries floats)."""


class ServiceError(Exception):
    """A request the service refuses: a protocol error code and a message naming the numbers."""

    def __init__(self, code: ErrorCode, message: str):
        super().__init__(message)
        self.code, self.message = code, message

    def to_message(self, others: list[str] | None = None) -> Error:
        return Error(code=self.code, message=self.message, others=others or [])


@dataclass
class Admission:
    """A validated open: the request, the population it belongs in, and its settings."""

    request: OpenSession
    """As asked, but for ``worlds``: the K granted."""
    key: PoolKey
    """Sessions with the same key share a population."""
    robot: RobotSpec
    tracker_config: TrackerConfig
    notice: str | None = None
    """Why fewer worlds were granted than asked for."""
    pool: Pool | None = None
    """A population with a free group; None when one must be built first (or is being built:
    its key is in :attr:`Gate.building`)."""
    peer: str = ""
    """The name the robot opened under ("" for none)."""


class Gate:
    """The caps and the frame budget over the service's populations. It reads the live registries
    it is given (``pools``: adopted populations by key; ``building``: worlds of each population on
    its way, by key) and changes neither."""

    def __init__(
        self,
        config: ServiceConfig,
        robots: dict[str, RobotSpec],
        objects: dict[str, ObjectSpec],
        frame_times: FrameTimes,
        pools: dict[PoolKey, Pool],
        building: dict[PoolKey, int],
        device: object,
    ):
        self.config, self.robots, self.objects, self.frame_times = config, robots, objects, frame_times
        self.pools, self.building, self.device = pools, building, device
        self.kinematics: dict[str, Kinematics] = {}
        """Each robot's own model (its joint layout), built once per robot."""
        self._opened: deque[float] = deque()
        """When sessions were opened in the last minute [s, monotonic]."""
        self._opened_by: dict[str, deque[float]] = {}
        """The same per peer name, for the peers that opened in the last minute."""
        self._built_by: dict[str, deque[float]] = {}
        """When populations were built for each peer name's opens, in the last minute [s, monotonic]."""

    # ------------------------------------------------------------------ the frame budget
    @property
    def budget_ms(self) -> float:
        """The p99 time all populations' steps may take together [ms]; inf without a budget."""
        cfg = self.config
        return 1e3 / cfg.rate_hz * cfg.budget_share if cfg.rate_hz else float("inf")

    def step_ms(self, pool: Pool) -> float:
        """A population's p99 step time [ms]: its own once it stepped enough, else the prediction."""
        if len(pool.step_ms) >= MEASURED_STEPS:
            return float(np.percentile(pool.step_ms, 99))
        return self.frame_times.predict(pool.worlds)

    def load_ms(self) -> float:
        """The p99 step times of every population stepping or being built, summed [ms]."""
        building = sum(self.frame_times.predict(w) for w in self.building.values())
        return sum(self.step_ms(p) for p in self.pools.values() if not p.failed) + building

    def free_worlds(self, sessions: int) -> int:
        """The most worlds (K) a session opened now in a new population would get, with ``sessions``
        open; 0 when full."""
        cfg = self.config
        if sessions >= cfg.max_sessions or len(self.pools) + len(self.building) >= cfg.max_populations:
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
            raise ServiceError(
                ErrorCode.CAPACITY, f"worlds: {asked} exceeds this service's limit of {cfg.max_worlds} (max_worlds)"
            )
        if not cfg.rate_hz:
            return (DEFAULT_WORLDS if asked == AUTO else asked), None
        joinable = [k.worlds for k, p in self.pools.items() if k.kind == kind and None in p.sessions]
        joinable += [k.worlds for k in self.building if k.kind == kind]
        if asked != AUTO and asked in joinable:
            return asked, None
        load, budget, g = self.load_ms(), self.budget_ms, cfg.groups
        room = (cfg.max_worlds - self._worlds_in_use()) // g
        if asked != AUTO and asked <= room and load + self.frame_times.predict(g * asked) <= budget:
            return asked, None
        cap = room if asked == AUTO else min(asked, room)
        sizes, before = ladder(cfg.min_worlds, cfg.max_worlds), self.frame_times.granted.get(str(kind))
        new = affordable_worlds(self.frame_times, load, budget, g, sizes, cap, before if asked == AUTO else None)
        best = max([new, *(k for k in joinable if k <= cap)])
        per = f"{cfg.rate_hz:g} Hz x {cfg.budget_share:g}"
        if asked == AUTO:
            if best:
                if best != before:
                    text = "worlds=auto: %d for %s (%s before), %.1f ms in use of the %.1f ms budget"
                    log.info(text, best, kind, before, load, budget)
                if not load:  # what an idle service grants, kept across starts
                    self.frame_times.granted[str(kind)] = best
                return best, None
            t = self.frame_times.predict(g * cfg.min_worlds)
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"worlds: no room in the frame budget of {budget:.1f} ms ({per}) on {self.device}: "
                f"{load:.1f} ms in use, and a population of {g} x {cfg.min_worlds} worlds (min_worlds) would "
                f"add about {t:.1f} ms (p99){self._budget_hint()}",
            )
        t = self.frame_times.predict(g * asked)
        why = (
            f"a population of {g} x {asked} worlds would step in about {t:.1f} ms (p99) on {self.device}; "
            f"with {load:.1f} ms in use that passes the frame budget of {budget:.1f} ms ({per})"
        )
        if asked > room:
            why = f"{g} x {asked} worlds pass the service's limit of {cfg.max_worlds} (max_worlds; {g * room} free)"
        if request.allow_fewer and best >= cfg.min_worlds:
            return best, f"worlds: {asked} asked, {best} granted: {why}"
        fit = f"at most {best} fit now (allow_fewer to take them)" if best else "none fit now"
        raise ServiceError(ErrorCode.CAPACITY, f"worlds: {why}; {fit}{self._budget_hint()}")

    def _budget_hint(self) -> str:
        """Which of the service's settings would admit more worlds, and what they are now."""
        cfg = self.config
        return (
            f". The service's settings that admit more: rate_hz (now {cfg.rate_hz:g}; 0: no frame budget),"
            f" budget_share ({cfg.budget_share:g}), groups ({cfg.groups}), min_worlds ({cfg.min_worlds})"
        )

    # ------------------------------------------------------------------ an open
    def admit(self, request: OpenSession, sessions: int, peer: str = "", peer_sessions: int = 0) -> Admission:
        """Validate an open with ``sessions`` open now, ``peer_sessions`` of them under ``peer``'s
        name (ServiceError with the field and the numbers), and find its population: one with a
        free group, or none when one must be built or is on its way."""
        robot = self._check(request, sessions)
        self._check_peer(peer, peer_sessions)
        tconf = self._tracker_config(request)
        self._check_q0(request, robot)
        overrides = tuple(sorted(request.overrides.items()))
        worlds, notice = self._grant(request, (request.robot, request.object, overrides))
        request = request.model_copy(update={"worlds": worlds})
        key = PoolKey(request.robot, request.object, worlds, overrides)
        admission = Admission(request, key, robot, tconf, notice, peer=peer)
        for k, pool in self.pools.items():
            if k.unbuilt() == key and pool.joinable:
                admission.pool = pool
                return admission
        if key in self.building:
            return admission
        cfg = self.config
        populations = len(self.pools) + len(self.building)
        if populations >= cfg.max_populations:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"populations: {populations} built, this service's limit is {cfg.max_populations} (max_populations)"
                " (sessions share one when robot, object, worlds and overrides match)",
            )
        in_use = self._worlds_in_use()
        if in_use + cfg.groups * worlds > cfg.max_worlds:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"worlds: no room for {cfg.groups} x {worlds} more worlds"
                f" ({in_use} in use, max_worlds {cfg.max_worlds})",
            )
        return admission

    def opened(self, peer: str = "") -> None:
        """Count an open against the per-minute caps (the service's, and its peer's)."""
        self._opened.append(time.monotonic())
        if peer:
            _recent(self._opened_by, peer).append(time.monotonic())

    def build_for(self, peer: str) -> None:
        """Count a population build for an open under ``peer``'s name, or refuse it past that
        peer's per-minute builds (an open under no name is not counted)."""
        if not peer:
            return
        built = _recent(self._built_by, peer)
        limit = self.config.max_builds_per_minute_per_peer
        if len(built) >= limit:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"builds: {len(built)} populations built for peer '{peer}' in the last 60 s, its limit is {limit}"
                " (max_builds_per_minute_per_peer; open with settings a population already has)",
            )
        built.append(time.monotonic())

    def _check_peer(self, peer: str, sessions: int) -> None:
        """Refuse an open under ``peer``'s name past that peer's own caps."""
        if not peer:
            return
        cfg = self.config
        if sessions >= cfg.max_sessions_per_peer:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"sessions: {sessions} open under peer '{peer}', its limit is {cfg.max_sessions_per_peer}"
                " (max_sessions_per_peer)",
            )
        opened = _recent(self._opened_by, peer)
        if len(opened) >= cfg.max_opens_per_minute_per_peer:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"opens: {len(opened)} under peer '{peer}' in the last 60 s, its limit is"
                f" {cfg.max_opens_per_minute_per_peer} (max_opens_per_minute_per_peer)",
            )

    def _check(self, request: OpenSession, sessions: int) -> RobotSpec:
        """The request's robot, after refusing what cannot be opened: a protocol version, robot,
        object, method or override not known here, or a cap reached."""
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
        if sessions >= self.config.max_sessions:
            limit = self.config.max_sessions
            raise ServiceError(
                ErrorCode.CAPACITY, f"sessions: {sessions} open, this service's limit is {limit} (max_sessions)"
            )
        now = time.monotonic()
        while self._opened and now - self._opened[0] > 60.0:
            self._opened.popleft()
        if len(self._opened) >= self.config.max_opens_per_minute:
            limit = self.config.max_opens_per_minute
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"opens: {len(self._opened)} in the last 60 s, this service's limit is {limit} (max_opens_per_minute)",
            )
        unknown = sorted(set(request.overrides) - set(_TUNABLE))
        if unknown:
            spelled = {n.rpartition(".")[2]: n for n in _TUNABLE}
            hint = [f"'{u}' is '{spelled[u]}'" for u in unknown if u in spelled]
            said = f" ({', '.join(hint)}: settings are named by their group)" if hint else f" (tunable: {_TUNABLE})"
            raise ServiceError(ErrorCode.BAD_REQUEST, f"overrides: unknown {unknown}{said}")
        return robot

    def _check_q0(self, request: OpenSession, robot: RobotSpec) -> None:
        if request.robot not in self.kinematics:
            self.kinematics[request.robot] = Kinematics(robot)
        d = self.kinematics[request.robot].layout.dof_count
        if request.q0 is not None and np.shape(request.q0) != (d,):
            got = np.shape(request.q0)[0]
            raise ServiceError(ErrorCode.BAD_REQUEST, f"q0: expected {d} joint positions, got {got}")

    @staticmethod
    def _tracker_config(request: OpenSession) -> TrackerConfig:
        """The session's tracker settings, refused with the field and the numbers before anything is built."""
        try:
            base = TrackerConfig(optimizer=OptimizerConfig(method=request.method))
            return tracker_config(request.overrides, base)
        except (ValueError, TypeError, OverflowError) as exc:
            raise ServiceError(ErrorCode.BAD_REQUEST, f"overrides: {exc}") from None


def _recent(times: dict[str, deque[float]], peer: str) -> deque[float]:
    """``peer``'s times of the last 60 s, older ones forgotten; peers gone quiet hold no memory."""
    now = time.monotonic()
    for name in [n for n, t in times.items() if not t or now - t[-1] > 60.0]:
        del times[name]
    recent = times.setdefault(peer, deque())
    while recent and now - recent[0] > 60.0:
        recent.popleft()
    return recent
