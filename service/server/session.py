"""One session's record: its robot, its group, its counters and queue, and what it reports (its
estimates and its status)."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from inhand_tracker.protocol import Estimate, RobotFrame, SessionStatus, TrackState
from inhand_tracker.service.tracker import GroupEstimates

if TYPE_CHECKING:
    from .pools import Pool

__all__ = ["Session"]

_CHECK_AFTER = 30
"""Frames before the model check speaks: the worlds settle into their grasp first."""


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
    """The name its robot opened under ("" for none): per-peer caps count it."""
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
    late_run: int = 0
    """Frames in a row that came behind the session's seq."""
    overflow_said: bool = False
    """Whether the session was told its worlds ran out of contact room."""
    heard: float = field(default_factory=time.monotonic)
    """When the session last received a frame (or opened) [s, monotonic]."""
    joints_off: dict[str, float] = field(default_factory=dict)
    """The model check: joints the worlds hold away from the robot's, by name: RMS [rad or m]."""

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
            joints_off=s.joints_off,
        )

    def estimate(self, frame: RobotFrame, est: GroupEstimates, latency: float) -> Estimate:
        """The session's estimate for ``frame``, from its group's row of a step's estimates."""
        s = self
        g = s.group
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
            latency_ms=latency,
            notice=s.notice,
        )
