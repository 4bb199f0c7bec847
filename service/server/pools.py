"""Populations in service and the sessions in their groups: each population holds G group slots
of one robot, object, K and tracker settings, and steps them in one graph replay. Here they are
keyed and built (on any thread, taking the device in turns with the loop); a session is one
robot's record in one group (its counters, queue, estimates and status). The manager that opens,
feeds and closes them is :mod:`.sessions`."""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from inhand_tracker.protocol import PRESENCE, SENSING, Estimate, RobotFrame, SessionStatus, TrackState
from inhand_tracker.service.tracker import GroupEstimates, Tracker, TrackerConfig
from inhand_tracker.sim_backend import ObjectSpec, Population, RobotSpec

from .config import PhysicsSettings

__all__ = [
    "MEASURED_STEPS",
    "NOBODY",
    "SILENT_AFTER",
    "Pool",
    "PoolKey",
    "Session",
    "Source",
    "Turn",
    "build_pool",
    "idle_pose",
]

MEASURED_STEPS = 100
"""A population's own p99 replaces the prediction for it once it stepped this often."""
SILENT_AFTER = 5
"""Steps a session may miss before its population stops waiting for it (until it sends again): a
co-tenant that opened and went quiet costs the others no wait."""


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


_CHECK_AFTER = 30
"""Frames before the model check speaks: the worlds settle into their grasp first."""


_SENSINGS = ("joints", "force", "touch")
"""The sensings a status reports residuals of, in :attr:`.GroupEstimates.residual`'s order."""


@dataclass(frozen=True)
class Source:
    """Who an open comes from."""

    key: str = ""
    """The fingerprint of the robot key the open proved; "" for an open without one."""
    known: bool = False
    """A robot the service was told of (``robot_keys``): it may use the room kept for them."""
    account: str = ""
    """What the per-peer caps count it under: ``robot key FINGERPRINT``, ``peer 'NAME'``, or ""
    (the service's caps only)."""


NOBODY = Source()
"""An open with no key and no name."""


@dataclass
class Session:
    id: str
    token: str
    """The session's secret: frames, close, status and pose queries must carry it."""
    robot: str
    object: str
    method: str
    pool: Pool
    group: int
    name: str = ""
    """The session's name: its ROS 2 topics and TF frame follow it."""
    peer: str = ""
    """The name its robot opened under ("" for none)."""
    source: Source = NOBODY
    """Who opened it: the robot key its open proved, whether the service keeps room for it, and
    what its per-peer caps count it under."""
    keyed: bool = False
    """Opened with a client key: its secret was agreed, and its estimates carry a MAC."""
    next_seq: int = 0
    epoch: int = 0
    """The robot's seq epoch (:attr:`protocol.RobotFrame.epoch`) the session follows."""
    replays: int = 0
    """Signed messages refused as replays."""
    fresh_after: dict[str, float] = field(default_factory=dict)
    """The newest stamp accepted per signed kind ("observation", "status", "close") [s]: a signed
    one not newer is a replay. Observations sharing a stamp are told apart by :attr:`seen_macs`."""
    seen_macs: deque = field(default_factory=lambda: deque(maxlen=64))
    """The MACs of the latest signed observations accepted."""
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
    stamps: deque = field(default_factory=lambda: deque(maxlen=31))
    """The robot clocks of the last frames accepted [s]: the robot's own rate."""
    latencies: deque = field(default_factory=lambda: deque(maxlen=1000))
    latest: Estimate | None = None
    contacts_explored: bool = False
    failed: str | None = None
    """Why the session's population failed; it takes no more frames then."""
    notice: str | None = None
    """Said to the robot with its next estimate, then cleared."""
    late_run: int = 0
    """Frames in a row that came behind the session's seq."""
    missed: int = 0
    """Steps of its population in a row that it sent no frame for: past :data:`SILENT_AFTER`, the
    population steps without waiting for it."""
    overflow_said: bool = False
    """Whether the session was told its worlds ran out of contact room."""
    heard: float = field(default_factory=time.monotonic)
    """When the session last received a frame (or opened) [s, monotonic]."""
    joints_off: dict[str, float] = field(default_factory=dict)
    """The model check: joints the worlds hold away from the robot's, by name: RMS [rad or m]."""
    residual: tuple[float, ...] = ()
    """What the lowest-cost world leaves unexplained after the latest frame, per sensing (joints,
    force, touch), :attr:`.GroupEstimates.residual`; and which of them the robot sent."""
    sensed: tuple[bool, ...] = ()

    def check_model(self, rms: np.ndarray, joints: tuple[str, ...], threshold: float) -> str | None:
        """Take the model check's latest RMS per joint (D,); once the session has a second of
        frames, the joints past ``threshold`` [rad or m] are named in the status. Returns what to
        say when that set grows, else None."""
        if self.frames < _CHECK_AFTER or not (self.joints_off or (rms > threshold).any()):
            return None  # the common case, every frame: nothing to name
        off = {name: round(float(r), 4) for name, r in zip(joints, rms, strict=True) if r > threshold}
        grew = set(off) - set(self.joints_off)
        self.joints_off = off
        if not grew:
            return None
        worst = sorted(off.items(), key=lambda kv: -kv[1])
        said = ", ".join(f"{n.rsplit(':', 1)[-1]} {r * 1e3:.0f}" for n, r in worst[:4])
        return (
            f"model: the worlds' joints run from the robot's ({said} mrad or mm RMS): the robot config's servos"
            f" are not the robot's; `inhand-tracker calibrate` fits them from a recording"
        )

    def status(self, budget_ms: float, load_ms: float) -> SessionStatus:
        """The session's status, beside the service's frame budget and load [ms]."""
        s = self
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
            replays=s.replays,
            errors=s.errors,
            latency_p50_ms=float(np.percentile(lat, 50)),
            latency_p99_ms=float(np.percentile(lat, 99)),
            cost=float(s.latest.cost) if s.latest else 0.0,
            spread_m=float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))),
            last_error=s.last_error,
            observations=s.observations,
            observations_stale=s.observations_stale,
            reseeds_by_observation=s.reseeds_by_observation,
            budget_ms=budget_ms,
            load_ms=load_ms,
            contacts_explored=s.contacts_explored,
            evidence=float(s.latest.evidence) if s.latest else 1.0,
            residuals={k: round(float(r), 6) for k, r, on in zip(_SENSINGS, s.residual, s.sensed) if on},  # noqa: B905 - none before the first frame
            joints_off=s.joints_off,
        )

    def estimate(self, frame: RobotFrame, est: GroupEstimates, latency: float) -> Estimate:
        """The session's estimate for ``frame``, from its group's row of a step's estimates."""
        s = self
        g = s.group
        # Made a dict only when the status is asked for, not every frame.
        s.residual, s.sensed = tuple(est.residual[g]), (True, frame.force is not None, frame.touch is not None)
        return Estimate(
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
            evidence=float(est.evidence[g]),
            dead_reckoning=float(est.reckoning[g]),
            latency_ms=latency,
            notice=s.notice,
        )
