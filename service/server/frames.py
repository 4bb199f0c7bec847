"""What a robot's frame may carry, checked against its robot before anything of it is used (each
field's shape, and values a real robot can send: joints near their limits, forces a hand can feel),
and the order frames are taken in (seq, gaps, late frames, re-syncs).

A value from one session never reaches the population it shares with others unchecked: one robot's
1e20 rad would turn every group's physics to NaN."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from inhand_tracker.protocol import SENSING, RobotFrame
from inhand_tracker.sim_backend import RobotLayout

if TYPE_CHECKING:
    from .pools import Session

__all__ = ["frame_problem", "in_order"]

_SLACK = 0.5
"""How far past a joint's limits a measured joint or a target may lie, as a share of its range
(encoders and commands overshoot a little; a corrupt value does not)."""


def frame_problem(frame: RobotFrame, layout: RobotLayout) -> str | None:
    """What is wrong with ``frame`` for a robot of ``layout``, naming the field and the numbers; None
    when nothing is."""
    d, l, z = layout.dof_count, layout.sensor_count, layout.zone_count
    for f in SENSING:
        value, shape = getattr(frame, f.name), f.shape(d, l, z)
        if value is not None and value.shape != shape:
            return f"RobotFrame.{f.name}: expected shape {shape}, got {value.shape} (seq {frame.seq})"
    slack = _SLACK * (layout.upper - layout.lower) + 1e-3
    low, high = layout.lower - slack, layout.upper + slack
    for name in ("controls", "q"):
        value = getattr(frame, name)
        bad = np.flatnonzero((value < low) | (value > high))
        if bad.size:
            j = int(bad[0])
            return (
                f"RobotFrame.{name}: joint '{layout.joint_names[j]}' = {value[j]:.4g} lies outside its limits "
                f"[{layout.lower[j]:.4g}, {layout.upper[j]:.4g}] by more than {slack[j]:.3g} (seq {frame.seq})"
            )
    for f in SENSING:
        value = getattr(frame, f.name)
        if f.bounds is not None and value is not None and value.size:
            low_, high_ = f.bounds
            if not ((value >= low_) & (value <= high_)).all():
                worst = value.flat[int(np.argmax(np.abs(value)))]
                return f"RobotFrame.{f.name}: expected {low_:g} to {high_:g}, got {worst:.4g} (seq {frame.seq})"
    return None


def in_order(session: Session, frame: RobotFrame, window: int, late_resync: int) -> bool:
    """Whether ``frame`` comes next in seq order: a duplicate or late one is counted and said,
    a gap counted. A seq beyond the window either way, or frames behind the session's for
    ``late_resync`` frames in a row (a robot that restarted its counter after a stray frame
    ran it ahead), re-synchronise the session to the robot's counter, with a notice."""
    last = session.pending[-1][0].seq if session.pending else session.next_seq - 1
    behind = frame.seq <= last
    session.late_run = session.late_run + 1 if behind else 0
    far = abs(frame.seq - last) > window
    if far or session.late_run >= late_resync:
        session.resyncs += 1
        session.stale += len(session.pending)
        session.pending.clear()
        why = f"beyond the service's window of {window}" if far else f"{session.late_run} frames in a row behind it"
        session.last_error = session.notice = (
            f"RobotFrame.seq: {frame.seq} after {last}, {why}: re-synchronised to the robot's counter"
        )
        session.next_seq, last, session.late_run = frame.seq, frame.seq - 1, 0
    elif behind:
        if frame.seq == last:
            session.duplicates += 1
        else:
            session.late += 1
            session.last_error = f"RobotFrame.seq: {frame.seq} is behind the session's {last}: dropped as late"
        return False
    session.gaps += frame.seq - last - 1
    return True
