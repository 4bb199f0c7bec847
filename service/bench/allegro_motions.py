"""The Allegro Hand's scripted motions: palm up, without a wrist (the hand of
``configs/robots/allegro_palm.toml``): the object lies on the palm and only the fingers and the
thumb move it, as in the field's palm-up reorientation tasks.

Every motion starts with the object lying on the palm, lets it settle, then does one thing and
opens the hand again:

- ``push``: the three fingers curl together against the object's far side, pushing it towards the
  wrist, and uncurl, to a different depth each time;
- ``slide``: the thumb swings in over the palm and slides the object sideways, then withdraws;
- ``turn``: the index and ring fingers curl in turn, pushing one corner and then the other, so
  the object turns as well as slides; the thumb stands by as a fence;
- ``knead``: a random one of those moves at a time, fingers and thumb at random depths.

Joint targets move with the minimum-jerk profile of :mod:`.motions`.
"""

from __future__ import annotations

import numpy as np

from inhand_tracker.sim_backend.kinematics import Kinematics
from inhand_tracker.sim_backend.objects import ObjectSpec

from .demos import FRAME_RATE, Demo
from .scripting import palm_rest_pose, start_script

__all__ = ["ALLEGRO_MOTION_KINDS", "make_allegro_motion"]

ALLEGRO_MOTION_KINDS = ("push", "slide", "turn", "knead")

PALM_CENTRE = np.array([0.0, 0.0, 0.1311])
"""Where the object lies on the mounted hand: on the palm's face, its far side just short of the
fingers' knuckles [m]."""
_DROP = 0.004
"""How far above the palm each motion starts the object [m]: it falls into place while the hand waits."""

_FINGERS = ("ff", "mf", "rf")
_THUMB_OUT = np.array([0.263, 0.53, 1.0, 1.25])
"""The thumb beside the palm, tip at the object's height, clear of it (rotation, abduction, flexions) [rad]."""
_THUMB_IN = np.array([0.45, 0.6, 1.644, 1.4])
"""The thumb swung in over the palm's edge: its tip where the object's side would be [rad]."""


def make_allegro_motion(kin: Kinematics, obj: ObjectSpec, kind: str, variant: int = 0, seconds: float = 15.0) -> Demo:
    """Script a ``kind`` motion (see :data:`ALLEGRO_MOTION_KINDS`) of about ``seconds`` for ``obj``
    lying on the palm; ``variant`` seeds where it lies and how far each move goes."""
    needed = {f"{f}j{k}" for f in (*_FINGERS, "th") for k in range(4)}
    index, rng, path = start_script(
        kin, ALLEGRO_MOTION_KINDS, kind, seconds, needed, (variant, 300), "push motion", "the Allegro Hand"
    )
    j = lambda *names: [index[n] for n in names]  # noqa: E731
    offset = np.array([*rng.uniform(-0.004, 0.004, 2), rng.uniform(-0.2, 0.2)])
    pose = palm_rest_pose(obj, offset, PALM_CENTRE, _DROP)
    start = path.q.copy()
    thumb = j("thj0", "thj1", "thj2", "thj3")
    flex = {f: j(f"{f}j1", f"{f}j2", f"{f}j3") for f in _FINGERS}
    # A curl of c bends the knuckle by c and the two outer joints a little more, so the medial
    # phalanx and fingertip sweep over the palm against the object's far side.
    curl = lambda c: np.array([c, 0.5 * c, 0.3 * c])  # noqa: E731

    path.hold("settle", 0.6)
    ready = start.copy()
    ready[thumb] = _THUMB_OUT
    path.move("carry", ready, 0.8)

    # The index and ring fingers stand beside the object: a turn swings one in (abduction) first.
    inward = {"ff": (index["ffj0"], -0.45), "rf": (index["rfj0"], 0.45)}

    def push(fingers: tuple[str, ...], depth: float) -> None:
        pushed = ready.copy()
        for f in fingers:
            pushed[flex[f]] = curl(depth)
            if len(fingers) == 1:
                pushed[inward[f][0]] = inward[f][1]
        path.move("carry", pushed, rng.uniform(0.7, 1.1))
        path.hold("carry", 0.2)
        path.move("carry", ready, 0.7)

    def slide(depth: float) -> None:
        slid = ready.copy()
        slid[thumb] = _THUMB_OUT + depth * (_THUMB_IN - _THUMB_OUT)
        path.move("carry", slid, rng.uniform(0.8, 1.2))
        path.hold("carry", 0.2)
        path.move("carry", ready, 0.8)

    end = (seconds - 1.6) * FRAME_RATE  # 1.6 s: open the hand and let the object lie
    while path.count < end:
        move = kind if kind != "knead" else rng.choice(("push", "slide", "turn"))
        if move == "push":
            push(_FINGERS, rng.uniform(0.5, 0.9))
        elif move == "slide":
            slide(rng.uniform(0.5, 1.0))
        else:  # turn: one side, then the other, the thumb fencing at half depth
            ready[thumb] = _THUMB_OUT + 0.4 * (_THUMB_IN - _THUMB_OUT)
            for side in rng.permutation(("ff", "rf")):
                push((side,), rng.uniform(0.7, 1.0))
            ready[thumb] = _THUMB_OUT
        path.hold("carry", 0.3)
    path.move("place", start, 1.0)
    path.hold("place", 0.6)
    return path.demo(f"{obj.name}_{kind}_{variant}", pose, start)
