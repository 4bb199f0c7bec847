"""Populations in service: each holds G group slots of one robot, object, K and tracker settings,
and steps them in one graph replay. Here they are keyed, built (on any thread, taking the device
in turns with the loop) and warmed up; sessions take their groups (:mod:`.sessions`)."""

from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from inhand_tracker.protocol import DEFAULT_WORLDS, PRESENCE, SENSING, OpenSession, Trajectory
from inhand_tracker.service.paths import DATA_DIR
from inhand_tracker.service.tracker import Tracker, TrackerConfig
from inhand_tracker.sim_backend import ObjectSpec, Population, RobotSpec
from inhand_tracker.sim_backend.kinematics import Kinematics

from .budget import calibrate
from .config import PhysicsSettings

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from .session import Session
    from .sessions import SessionManager

__all__ = ["MEASURED_STEPS", "Pool", "PoolKey", "Turn", "build_pool", "idle_pose", "warm_up"]

MEASURED_STEPS = 100
"""A population's own p99 replaces the prediction for it once it stepped this often."""
_CALIBRATION = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
"""What the frame times are calibrated on: a pick and place, the hand in contact for most of it."""


@dataclass(frozen=True)
class PoolKey:
    """What makes sessions share a population: robot, object, K and the tracker's overrides."""

    robot: str
    object: str
    worlds: int
    overrides: tuple[tuple[str, int | float | bool], ...] = ()
    """The session's tracker overrides, sorted by name."""
    serial: int = 0
    """Which population of this kind: 0 until built and adopted, then a number never reused, so
    a new population's key never repeats a dropped one's."""

    @property
    def kind(self) -> tuple[str, str, tuple]:
        """Robot, object and overrides: populations of one kind differ only in K."""
        return self.robot, self.object, self.overrides

    def unbuilt(self) -> PoolKey:
        """The key as an open asks for it, before a population of it was adopted."""
        return replace(self, serial=0)


@dataclass
class Pool:
    """One population with a fixed number of group slots, and what its robots last sent."""

    key: PoolKey
    tracker: Tracker
    sessions: list[Session | None]
    sensing: dict[str, np.ndarray]
    """What every group's robot last sent, each field of protocol.SENSING as (G, ...): a group
    without a frame this tick holds its last controls and joints (the start pose at first), and
    touch it did not send is zero."""
    present: dict[str, np.ndarray]
    """Which presence groups each group's robot sent in its last frame, {"force": (G,) bool, ...}."""

    failed: bool = False
    """Its step raised: it steps no more and takes no new sessions."""
    step_ms: deque = field(default_factory=lambda: deque(maxlen=3 * MEASURED_STEPS))
    """Its latest steps' times [ms]."""
    steps: int = 0

    @property
    def active(self) -> list[Session]:
        return [s for s in self.sessions if s is not None]

    @property
    def worlds(self) -> int:
        return self.tracker.G * self.tracker.K

    @property
    def joinable(self) -> bool:
        """It takes a new session: a group is free and it has not failed."""
        return None in self.sessions and not self.failed


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


def idle_pose(obj: ObjectSpec) -> np.ndarray:
    """Where an idle group's object rests: on the table, out of the hand's reach, where nothing happens, (7,)."""
    return np.array([0.3, 0.0, -float(obj.mesh.bounds[0, 2]), 0, 0, 0, 1], np.float32)


def build_pool(
    key: PoolKey,
    robot: RobotSpec,
    obj: ObjectSpec,
    tracker_config: TrackerConfig,
    method: str,
    groups: int,
    device: str,
    physics: PhysicsSettings,
    turn: Turn,
) -> Pool:
    """A population for ``key`` with every group idle and its graphs captured; safe on a thread of
    its own (it touches no shared state; its device work takes ``turn``)."""
    pop = Population(robot, obj, physics.population(groups, key.worlds, device), turn=turn)
    with turn:
        tracker = Tracker(pop, tracker_config, methods=[method] * groups)
        g = pop.G
        sensing = {f.name: np.zeros((g, *f.shape(pop.D, pop.L, pop.Z)), np.float32) for f in SENSING}
        for f in SENSING:
            if f.per == "joint":
                sensing[f.name][:] = pop.layout.default_q
        present = {p: np.zeros(g, bool) for p in PRESENCE}
        idle = np.tile(idle_pose(obj), (g, 1))
        tracker.start(idle, sensing["q"])
        tracker.capture()  # here, not in the loop's first step of it
        tracker.start(idle, sensing["q"])
    return Pool(key, tracker, [None] * g, sensing, present)


def warm_up(manager: SessionManager) -> None:
    """Compile the kernels before any robot waits on an open (minutes on a cold cache), and,
    with a frame budget, measure the step time at a few population sizes unless this device's
    are cached. One world per group on the CPU without a budget; the sizes ``auto`` grants
    first on CUDA, where some of Newton's kernels are compiled per size."""
    traj = Trajectory.load(_CALIBRATION)
    replay = traj.robot in manager.robots and traj.object in manager.objects
    robot, obj = (traj.robot, traj.object) if replay else (next(iter(manager.robots)), next(iter(manager.objects)))
    cfg, cuda = manager.config, manager.device.is_cuda
    if not cfg.rate_hz:
        sizes = [DEFAULT_WORLDS if cuda else 1]
    else:
        sizes = [k for k in ((8, 128, 1024) if cuda else (1, 8)) if cfg.groups * k <= cfg.max_worlds]
    measure = cfg.rate_hz and any(cfg.groups * k not in manager.frame_times.points for k in sizes)
    if not replay and measure:
        log.warning(
            "frame times: calibrating with robot '%s' holding still (the bundled motion is the '%s' robot's);"
            " the populations' own steps will correct them", robot, traj.robot,
        )  # fmt: skip
    for k in sizes if measure else sizes[:1]:
        request = OpenSession(robot=robot, object=obj, p0=traj.truth.initial_pose, worlds=k)
        key, spec, shape = PoolKey(robot, obj, k), manager.robots[robot], manager.objects[obj]
        tracker = build_pool(key, spec, shape, TrackerConfig(), request.method, cfg.groups, cfg.device, cfg.physics,
                             manager.turn).tracker  # fmt: skip
        if measure:
            q0 = manager.gate.kinematics.setdefault(robot, Kinematics(manager.robots[robot])).layout.default_q
            ms = calibrate(tracker, traj if replay else None, q0, idle_pose(manager.objects[obj]))
            manager.frame_times.observe(tracker.G * tracker.K, ms, weight=1.0)
            log.info("frame times: %d worlds step in %.1f ms (p99) on %s", tracker.G * tracker.K, ms, manager.device)
        del tracker
    if measure:
        manager.frame_times.save(cfg.frame_time_cache)
