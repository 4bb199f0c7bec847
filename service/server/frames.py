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

__all__ = ["frame_problem", "fresh", "in_order"]

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
    ran it ahead), re-synchronise the session to the robot's counter, with a notice. A signed
    frame re-synchronises only forward or in a newer epoch (:attr:`protocol.RobotFrame.epoch`):
    only the robot can sign those, while any relay can replay what it recorded."""
    last = session.pending[-1][0].seq if session.pending else session.next_seq - 1
    signed = bool(frame.mac)
    if signed and frame.epoch != session.epoch:
        if frame.epoch < session.epoch:
            return _replayed(session, frame, f"epoch {frame.epoch}, the session's is {session.epoch}")
        why = f"epoch {frame.epoch}: the robot restarted its counter"
        session.epoch = frame.epoch
        return _resync(session, frame, last, why)
    behind = frame.seq <= last
    session.late_run = session.late_run + 1 if behind else 0
    far = abs(frame.seq - last) > window
    if signed and behind and (far or session.late_run >= late_resync):
        return _replayed(session, frame, f"behind the session's {last} in its epoch {session.epoch}")
    if far or session.late_run >= late_resync:
        why = f"beyond the service's window of {window}" if far else f"{session.late_run} frames in a row behind it"
        return _resync(session, frame, last, why)
    if behind:
        if frame.seq == last:
            session.duplicates += 1
        else:
            session.late += 1
            session.last_error = f"RobotFrame.seq: {frame.seq} is behind the session's {last}: dropped as late"
        return False
    session.gaps += frame.seq - last - 1
    return True


def _resync(session: Session, frame: RobotFrame, last: int, why: str) -> bool:
    """Take the robot's counter from ``frame`` on, dropping what was queued; said once."""
    session.resyncs += 1
    session.stale += len(session.pending)
    session.pending.clear()
    session.last_error = session.notice = (
        f"RobotFrame.seq: {frame.seq} after {last}, {why}: re-synchronised to the robot's counter"
    )
    session.next_seq, session.late_run = frame.seq, 0
    return True


def _replayed(session: Session, frame: RobotFrame, why: str) -> bool:
    session.replays += 1
    session.last_error = f"RobotFrame.seq: {frame.seq}, {why}: refused as a replay"
    return False


def fresh(session: Session, kind: str, stamp: float, mac: str) -> bool:
    """Whether a signed ``kind`` message ("observation", "status", "close") stamped ``stamp`` [s]
    is new: newer than the last accepted, or (observations, several of which may share a frame's
    stamp) as new and not seen. A replay is counted; the accepted stamp and MAC are kept."""
    newest = session.fresh_after.get(kind, -1.0)
    if stamp < newest or (stamp == newest and (kind != "observation" or mac in session.seen_macs)):
        session.replays += 1
        session.last_error = f"{kind}: stamp {stamp:.6f} s, not newer than {newest:.6f} s accepted: refused as a replay"
        return False
    session.fresh_after[kind] = stamp
    if kind == "observation":
        session.seen_macs.append(mac)
    return True
