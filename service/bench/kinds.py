"""Every scripted motion by its kind: a suite names kinds, and each kind belongs to one hand's
scripts (the procedural hand's demos and motions, the Shadow Hand's, the Allegro Hand's)."""

from __future__ import annotations

from collections.abc import Callable

from inhand_tracker.sim_backend.kinematics import Kinematics
from inhand_tracker.sim_backend.objects import ObjectSpec

from .allegro_motions import ALLEGRO_MOTION_KINDS, make_allegro_motion
from .demos import DEMO_KINDS, Demo, make_demo
from .motions import MOTION_KINDS, make_motion
from .shadow_motions import SHADOW_MOTION_KINDS, make_shadow_motion

__all__ = ["KINDS", "make_kind"]

_Maker = Callable[[Kinematics, ObjectSpec, str, int, float, float], Demo]
KINDS: dict[str, _Maker] = {
    **{k: make_demo for k in DEMO_KINDS},  # the only scripts paced: a pick and place's speed is a setting
    **{k: lambda kin, obj, kind, v, s, _pace: make_motion(kin, obj, kind, v, s) for k in MOTION_KINDS},
    **{k: lambda kin, obj, kind, v, s, _pace: make_shadow_motion(kin, obj, kind, v, s) for k in SHADOW_MOTION_KINDS},
    **{k: lambda kin, obj, kind, v, s, _pace: make_allegro_motion(kin, obj, kind, v, s) for k in ALLEGRO_MOTION_KINDS},
}
"""Each kind's maker: (kinematics, object, kind, variant, seconds, pace) -> the scripted motion."""


def make_kind(kin: Kinematics, obj: ObjectSpec, kind: str, variant: int, seconds: float, pace: float) -> Demo:
    """The scripted motion of ``kind`` (:data:`KINDS`) for ``kin``'s hand and ``obj``."""
    if kind not in KINDS:
        raise ValueError(f"motion kind: expected one of {sorted(KINDS)}, got {kind!r}")
    return KINDS[kind](kin, obj, kind, variant, seconds, pace)
