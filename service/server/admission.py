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
from inhand_tracker.service.tracker.settings import registry, robot_defaults, tracker_config, unchecked_palms
from inhand_tracker.sim_backend import ObjectSpec, RobotSpec
from inhand_tracker.sim_backend.kinematics import Kinematics

from .budget import FrameTimes, affordable_worlds, ladder
from .config import ServiceConfig
from .pools import MEASURED_STEPS, NOBODY, Pool, PoolKey, Session, Source

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
    source: Source = NOBODY
    """Who opened it (the robot key its open proved)."""


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
        self.defaults = {name: robot_defaults(spec) for name, spec in robots.items()}
        """Each robot's tracker settings (its config's ``[tracker]`` table), checked once on load."""
        for name in unchecked_palms(robots):
            log.info(
                f"robot '{name}' carries objects on its palm and its config gives no [tracker] table: its sessions"
                " run the tracker's defaults held open loop until the robot first feels the object"
                " (optimizer.until_felt), which on a palm-up hand that feels it only through a few coarse zones or"
                " a passing fingertip can track worse than one open-loop world where that world starts close;"
                " `inhand-tracker check-settings` measures on a few grasps with motion capture which settings it"
                " needs (`tracker = {}` in the config says the defaults were chosen)"
            )
        self.kinematics: dict[str, Kinematics] = {}
        """Each robot's own model (its joint layout), built once per robot."""
        self._opened: deque[float] = deque()
        """When sessions were opened in the last minute by robots the service keeps no room for [s, monotonic]."""
        self._opened_by: dict[str, deque[float]] = {}
        """The same per account (a robot key, or a peer name), for the accounts that opened in the last minute."""
        self._built_by: dict[str, deque[float]] = {}
        """When populations were built for each account's opens, in the last minute [s, monotonic]."""

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

    def _grant(self, request: OpenSession, kind: tuple, source: Source = NOBODY) -> tuple[int, str | None]:
        """The K an open gets, and why it is fewer than asked for (when it is): what was asked,
        if it fits the frame budget; a population of the same ``kind`` (robot, object,
        overrides) with a free group costs nothing more; else the most that fits, for "auto" or
        ``allow_fewer``; else a refusal naming the numbers. An open from a peer the service keeps
        no room for fits only the share of the budget not kept (as of the populations)."""
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
        share = self._share(source)
        load, budget, g = self.load_ms(), self.budget_ms * share, cfg.groups
        room = (cfg.max_worlds - self._worlds_in_use()) // g
        if asked != AUTO and asked <= room and load + self.frame_times.predict(g * asked) <= budget:
            return asked, None
        cap = room if asked == AUTO else min(asked, room)
        sizes, before = ladder(cfg.min_worlds, cfg.max_worlds), self.frame_times.granted.get(str(kind))
        new = affordable_worlds(self.frame_times, load, budget, g, sizes, cap, before if asked == AUTO else None)
        best = max([new, *(k for k in joinable if k <= cap)])
        kept = f" x {share:.3g} not kept for robot_keys" if share < 1 else ""
        per = f"{cfg.rate_hz:g} Hz x {cfg.budget_share:g}{kept}"
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

    def _share(self, source: Source) -> float:
        """The share of the frame budget an open from ``source`` may fill: all of it for a robot the
        service keeps room for (or when it keeps none), else what the kept populations leave."""
        cfg = self.config
        if source.known or not cfg.robot_keys:
            return 1.0
        return max(0.0, 1.0 - cfg.reserved_populations / cfg.max_populations)

    def _budget_hint(self) -> str:
        """Which of the service's settings would admit more worlds, and what they are now."""
        cfg = self.config
        return (
            f". The service's settings that admit more: rate_hz (now {cfg.rate_hz:g}; 0: no frame budget),"
            f" budget_share ({cfg.budget_share:g}), groups ({cfg.groups}), min_worlds ({cfg.min_worlds})"
        )

    # ------------------------------------------------------------------ an open
    def admit(
        self, request: OpenSession, sessions: list[Session], peer: str = "", source: Source = NOBODY
    ) -> Admission:
        """Validate an open from ``source`` under ``peer``'s name with ``sessions`` open now
        (ServiceError with the field and the numbers), and find its population: one with a free
        group, or none when one must be built or is on its way."""
        robot = self._check(request, sessions, source)
        self._check_account(source.account, sum(s.source.account == source.account for s in sessions))
        tconf = self._tracker_config(request)
        self._check_q0(request, robot)
        overrides = tuple(sorted(request.overrides.items()))
        worlds, notice = self._grant(request, (request.robot, request.object, overrides), source)
        request = request.model_copy(update={"worlds": worlds})
        key = PoolKey(request.robot, request.object, worlds, overrides)
        admission = Admission(request, key, robot, tconf, notice, peer=peer, source=source)
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
        kept = cfg.reserved_populations if cfg.robot_keys and not source.known else 0
        theirs = sum(not any(s and s.source.known for s in p.sessions) for p in self.pools.values())
        if kept and theirs + len(self.building) >= cfg.max_populations - kept:
            raise ServiceError(ErrorCode.CAPACITY, f"populations: {theirs + len(self.building)} built for peers not in"
                               f" robot_keys, their limit is {cfg.max_populations - kept} (max_populations less"
                               " reserved_populations, kept for the robots in robot_keys)")  # fmt: skip
        in_use = self._worlds_in_use()
        if in_use + cfg.groups * worlds > cfg.max_worlds:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"worlds: no room for {cfg.groups} x {worlds} more worlds"
                f" ({in_use} in use, max_worlds {cfg.max_worlds})",
            )
        return admission

    def opened(self, source: Source) -> None:
        """Count an open against the per-minute caps (the service's, unless the service keeps room
        for its robot, and its account's)."""
        if not source.known:
            self._opened.append(time.monotonic())
        if source.account:
            _recent(self._opened_by, source.account).append(time.monotonic())

    def build_for(self, source: Source) -> None:
        """Count a population build for an open from ``source``, or refuse it past its account's
        per-minute builds (an open under no name and no key is not counted)."""
        if not source.account:
            return
        built = _recent(self._built_by, source.account)
        limit = self.config.max_builds_per_minute_per_peer
        if len(built) >= limit:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"builds: {len(built)} populations built for {source.account} in the last 60 s, its limit is {limit}"
                " (max_builds_per_minute_per_peer; open with settings a population already has)",
            )
        built.append(time.monotonic())

    def _check_account(self, account: str, sessions: int) -> None:
        """Refuse an open past its account's own caps (a robot key's, or a peer name's)."""
        if not account:
            return
        cfg = self.config
        if sessions >= cfg.max_sessions_per_peer:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"sessions: {sessions} open under {account}, its limit is {cfg.max_sessions_per_peer}"
                " (max_sessions_per_peer)",
            )
        opened = _recent(self._opened_by, account)
        if len(opened) >= cfg.max_opens_per_minute_per_peer:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"opens: {len(opened)} under {account} in the last 60 s, its limit is"
                f" {cfg.max_opens_per_minute_per_peer} (max_opens_per_minute_per_peer)",
            )

    def _check_room(self, sessions: list[Session], source: Source) -> None:
        """Refuse an open past the service's caps: its sessions, and for a robot it keeps no room
        for, the sessions and opens per minute of all such robots together."""
        cfg, n = self.config, len(sessions)
        if n >= cfg.max_sessions:
            raise ServiceError(
                ErrorCode.CAPACITY, f"sessions: {n} open, this service's limit is {cfg.max_sessions} (max_sessions)"
            )
        if source.known:
            return
        kept = cfg.reserved_sessions if cfg.robot_keys else 0
        theirs = sum(not s.source.known for s in sessions)
        if kept and theirs >= cfg.max_sessions - kept:
            raise ServiceError(ErrorCode.CAPACITY, f"sessions: {theirs} open by peers not in robot_keys, their limit"
                               f" is {cfg.max_sessions - kept} (max_sessions less reserved_sessions, kept for the"
                               " robots in robot_keys)")  # fmt: skip
        now = time.monotonic()
        while self._opened and now - self._opened[0] > 60.0:
            self._opened.popleft()
        if len(self._opened) >= cfg.max_opens_per_minute:
            raise ServiceError(
                ErrorCode.CAPACITY,
                f"opens: {len(self._opened)} in the last 60 s, this service's limit is {cfg.max_opens_per_minute}"
                " (max_opens_per_minute)" + (" for peers not in robot_keys" if cfg.robot_keys else ""),
            )

    def _check(self, request: OpenSession, sessions: list[Session], source: Source) -> RobotSpec:
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
        self._check_room(sessions, source)
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

    def _tracker_config(self, request: OpenSession) -> TrackerConfig:
        """The session's tracker settings: its robot's, changed by its overrides; refused with the
        field and the numbers before anything is built."""
        try:
            base = TrackerConfig(optimizer=OptimizerConfig(method=request.method))
            return tracker_config(self.defaults[request.robot] | request.overrides, base)
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
