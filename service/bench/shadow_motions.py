"""The Shadow Hand's scripted motions: it carries the object on its upturned palm (the hand of
``configs/robots/shadow_hand.toml``), so that the tracker is measured on a second real hand whose
grasps are not pinches.

Every motion starts with the object lying on the open palm, its long side along the hand, lets it
settle, then does one thing such a hand does with what it carries, and opens again:

- ``cradle``: curls the fingers and thumb into a loose fence and tilts the wrist to and fro, so the
  object rocks and slides between palm, fingers and thumb;
- ``roll``: curls the fingers one after another and swings the thumb across, pushing the object
  over the palm;
- ``tilt``: keeps the fingers half curled and tilts the wrist in small random steps, so the object
  slides on the palm against them;
- ``cup``: closes fingers and thumb around the object, tilts the hand while holding it, then
  loosens the hold and closes again.

Joint targets move with the minimum-jerk profile of :mod:`.motions`.
"""

from __future__ import annotations

import numpy as np

from inhand_tracker.sim_backend.kinematics import Kinematics
from inhand_tracker.sim_backend.objects import ObjectSpec

from .demos import FRAME_RATE, Demo
from .scripting import palm_rest_pose, start_script

__all__ = ["DISTAL_COUPLING", "SHADOW_MOTION_KINDS", "distal_coupling", "make_shadow_motion", "rest_pose"]

SHADOW_MOTION_KINDS = ("cradle", "roll", "tilt", "cup")

PALM_CENTRE = np.array([0.0, -0.13, 0.147])
"""Where the object lies on the open hand, as the robot config mounts it: on the palm's face
where the fingers begin [m]."""
_DROP = 0.008
"""How far above the hand each motion starts the object [m]: it falls into place while the hand
waits. Laid exactly on the palm and the fingers' knuckles, a pose a millimetre off overlaps them,
and the two engines push it out differently (Newton's contacts flipped a brick off the hand)."""

_FINGERS = ("FF", "MF", "RF", "LF")
DISTAL_COUPLING = 0.00805 / 0.00705
"""A finger's distal joint angle per middle joint angle: the ratio of the model's coupling tendon."""


def rest_pose(obj: ObjectSpec, offset: np.ndarray) -> np.ndarray:
    """``obj`` just above the Shadow Hand's palm, shifted by ``offset`` (x, y [m], yaw [rad]), (7,)
    (:func:`.scripting.palm_rest_pose`)."""
    return palm_rest_pose(obj, offset, PALM_CENTRE, _DROP)


def distal_coupling(lay) -> tuple[list[int], list[int]] | None:
    """The Shadow Hand's middle joints (J1) and the distal joints (J0) its tendons make follow them,
    by index in the robot's order; None for a robot without them."""
    index = {name.rsplit(":", 1)[-1]: i for i, name in enumerate(lay.joint_names)}
    pairs = [(index.get(f"{f}J1"), index.get(f"{f}J0")) for f in _FINGERS]
    if any(m is None or d is None for m, d in pairs):
        return None
    return [m for m, _ in pairs], [d for _, d in pairs]  # type: ignore[misc]


def make_shadow_motion(kin: Kinematics, obj: ObjectSpec, kind: str, variant: int = 0, seconds: float = 20.0) -> Demo:
    """Script a ``kind`` motion (see :data:`SHADOW_MOTION_KINDS`) of about ``seconds`` for ``obj``
    lying on the palm; ``variant`` seeds where it lies and how far each move goes."""
    needed = {"WRJ0", "WRJ1", *(f"{f}J{k}" for f in _FINGERS for k in range(3)), "THJ4", "THJ3", "THJ1", "THJ0"}
    index, rng, path = start_script(
        kin, SHADOW_MOTION_KINDS, kind, seconds, needed, (variant, 200), "palm motion", "the Shadow Hand"
    )
    j = lambda *names: [index[n] for n in names]  # noqa: E731
    pose = rest_pose(obj, np.array([*rng.uniform(-0.004, 0.004, 2), rng.uniform(-0.15, 0.15)]))
    start = path.q.copy()
    middle, distal = j(*(f"{f}J1" for f in _FINGERS)), j(*(f"{f}J0" for f in _FINGERS))

    def move(phase: str, target: np.ndarray, seconds: float) -> None:
        """``path.move``, with the distal joints where the tendon takes them."""
        target = target.copy()
        target[distal] = DISTAL_COUPLING * target[middle]
        path.move(phase, target, seconds)

    path.hold("settle", 0.6)

    curl = j(*(f"{f}J{k}" for f in _FINGERS for k in (2, 1)))
    fence = start.copy()
    fence[curl] = rng.uniform(0.95, 1.25)
    fence[j("THJ4", "THJ3")] = rng.uniform(0.8, 1.0), rng.uniform(0.9, 1.2)
    grip = start.copy()
    grip[curl] = 1.2
    grip[j("THJ4", "THJ3", "THJ1", "THJ0")] = 1.0, 1.1, 0.3, -0.6

    end = (seconds - 1.6) * FRAME_RATE  # 1.6 s: open the hand and let the object lie
    if kind == "cup":
        move("carry", grip, 1.0)
    else:
        move("carry", fence, 0.8)
    held = path.q.copy()
    while path.count < end:
        if kind == "cradle":
            for sign in (1.0, -1.0):
                rocked = held.copy()
                rocked[j("WRJ0")] = sign * rng.uniform(0.15, 0.35)
                rocked[j("WRJ1")] = rng.uniform(-0.3, 0.1)
                move("carry", rocked, rng.uniform(0.8, 1.3))
                path.hold("carry", 0.2)
            move("carry", held, 0.8)
        elif kind == "roll":
            wave = held.copy()
            for f in rng.permutation(_FINGERS):
                wave[j(f"{f}J2", f"{f}J1")] += rng.uniform(0.15, 0.35)
                move("carry", wave, 0.4)
            move("carry", held, 0.6)
            swept = held.copy()
            swept[j("THJ4", "THJ3")] += rng.uniform(0.1, 0.25), rng.uniform(-0.3, -0.1)
            move("carry", swept, 0.7)
            move("carry", held, 0.6)
        elif kind == "tilt":
            step = held.copy()
            step[j("WRJ0")] = rng.uniform(-0.2, 0.2)
            step[j("WRJ1")] = rng.uniform(-0.3, 0.1)
            move("carry", step, rng.uniform(0.5, 1.0))
            path.hold("carry", 0.2)
        else:  # cup
            tilted = held.copy()
            tilted[j("WRJ0")] = rng.choice((-1.0, 1.0)) * rng.uniform(0.2, 0.4)
            move("carry", tilted, 1.0)
            move("carry", held, 1.0)
            eased = held.copy()
            eased[curl] = held[curl] - rng.uniform(0.3, 0.6)
            move("carry", eased, 0.5)
            path.hold("carry", 0.3)
            move("carry", held, 0.4)
        path.hold("carry", 0.3)
    move("place", start, 1.0)
    path.hold("place", 0.6)
    return path.demo(f"{obj.name}_{kind}_{variant}", pose, start)
