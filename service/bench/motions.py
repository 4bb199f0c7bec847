"""Scripted motions for the cross-engine suite, of their own (only the scripting helpers are the
demos'), so that the tracker is not only measured on the motions it was developed on.

Every motion picks the object up with a pinch, then does one thing a real hand does with what it
holds, then sets it down and lets go:

- ``wrist_roll``: rolls the wrist one way and the other, so gravity pulls the object across the pads;
- ``tilt_shake``: tilts the hand forward and shakes it sideways, a few quick strokes;
- ``loosen``: eases the squeeze until the object sags in the pads, then squeezes again;
- ``twist``: turns the object with the fingers while the wrist yaws the other way.

Joint targets move between waypoints with a minimum-jerk profile (zero velocity and acceleration
at both ends), the way motion planners and teleoperation filters shape commands.
"""

from __future__ import annotations

import numpy as np

from inhand_tracker.sim_backend.grasp import SQUEEZE_JOINTS, plan_pinch
from inhand_tracker.sim_backend.kinematics import Kinematics
from inhand_tracker.sim_backend.objects import ObjectSpec

from .demos import FRAME_RATE, Demo, Script
from .scripting import minimum_jerk

__all__ = ["MOTION_KINDS", "make_motion"]

MOTION_KINDS = ("wrist_roll", "tilt_shake", "loosen", "twist")

_WRIST_YAW, _WRIST_PITCH, _WRIST_ROLL = 3, 4, 5
_ABDUCTION = (6, 10, 14)
_THUMB_SWING = 18


def make_motion(kin: Kinematics, obj: ObjectSpec, kind: str, variant: int = 0, seconds: float = 20.0) -> Demo:
    """Script a ``kind`` motion (see :data:`MOTION_KINDS`) of about ``seconds`` for ``obj`` on the
    table; ``variant`` seeds where the object lies and how far each move goes."""
    if kind not in MOTION_KINDS:
        raise ValueError(f"motion kind: expected one of {MOTION_KINDS}, got {kind!r}")
    if not (6.0 <= seconds <= 120.0):
        raise ValueError(f"motion seconds: expected 6 to 120, got {seconds}")
    lay = kin.layout
    rng = np.random.default_rng([variant, 100 + MOTION_KINDS.index(kind)])
    rest_z = -float(obj.mesh.bounds[0, 2])
    wrist = np.array([*rng.uniform(-0.04, 0.04, 2), 0.3, 0.0, 0.0, 0.0])
    wrist[2] += rest_z - plan_pinch(kin, obj, wrist_q=wrist).object_pose[2]
    grasp = plan_pinch(kin, obj, wrist_q=wrist)
    start = lay.default_q.copy()
    start[:3] = wrist[0], wrist[1], wrist[2] + 0.1
    path = Script(start, lay.lower, lay.upper, profile=minimum_jerk)

    above = start.copy()
    above[2] = wrist[2]
    path.move("reach", above, 1.0)
    path.move("close", grasp.q_touch, 0.7)
    path.move("squeeze", grasp.q_squeeze, 0.2)
    path.hold("squeeze", 0.3)
    held = grasp.q_squeeze.copy()
    held[2] += 0.05
    path.move("lift", held, 1.0)
    path.hold("lift", 0.3)

    end = (seconds - 3.0) * FRAME_RATE  # 3 s: set down, let go, rise
    cycle = 0
    while path.count < end:
        cycle += 1
        if cycle % 2 == 0:
            # Between two of its moves a hand carries what it holds somewhere else, calmly: a
            # script that only shook would shake any object out of an open-loop grasp.
            moved = held.copy()
            moved[:2] += rng.uniform(-0.03, 0.03, 2)
            path.move("carry", moved, 1.2)
            held = moved
        elif kind == "wrist_roll":
            angle = rng.uniform(0.35, 0.6)
            for sign in (1.0, -1.0):
                rolled = held.copy()
                rolled[_WRIST_ROLL] += sign * angle
                path.move("carry", rolled, rng.uniform(0.8, 1.4))
                path.hold("carry", 0.3)
            path.move("carry", held, 1.0)
        elif kind == "tilt_shake":
            tilted = held.copy()
            tilted[_WRIST_PITCH] += rng.uniform(0.2, 0.35)
            path.move("carry", tilted, 0.8)
            for _ in range(2):
                stroke = tilted.copy()
                stroke[1] += rng.choice((-1.0, 1.0)) * rng.uniform(0.015, 0.03)
                path.move("carry", stroke, 0.3)
                path.move("carry", tilted, 0.3)
            path.move("carry", held, 0.8)
        elif kind == "loosen":
            eased = held.copy()
            ease = rng.uniform(0.45, 0.7)  # how much of the squeeze is let off
            eased[SQUEEZE_JOINTS] = held[SQUEEZE_JOINTS] + ease * (grasp.q_touch - grasp.q_squeeze)[SQUEEZE_JOINTS]
            path.move("carry", eased, 0.6)
            path.hold("carry", 0.4)
            path.move("carry", held, 0.3)
        else:  # twist
            turn = rng.uniform(0.2, 0.35)
            twisted = held.copy()
            twisted[list(_ABDUCTION)] -= turn
            twisted[_THUMB_SWING] -= turn
            twisted[_WRIST_YAW] += 0.5 * turn
            path.move("carry", twisted, 1.5)
            path.hold("carry", 0.3)
            path.move("carry", held, 1.5)
        path.hold("carry", 0.4)
    down = held.copy()
    down[2] -= 0.05
    down[_WRIST_ROLL] = down[_WRIST_PITCH] = down[_WRIST_YAW] = 0.0
    path.move("place", down, 1.0)
    path.let_go(grasp.q_touch)
    return path.demo(f"{obj.name}_{kind}_{variant}", grasp.object_pose, start)
