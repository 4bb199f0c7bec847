"""What the hands' scripted motions share: the minimum-jerk profile, an object at rest on a palm,
and a script's start (its checks, its joints by name, its random numbers)."""

from __future__ import annotations

import numpy as np

from inhand_tracker.sim_backend.kinematics import Kinematics
from inhand_tracker.sim_backend.objects import ObjectSpec

from .demos import Script

__all__ = ["minimum_jerk", "palm_rest_pose", "start_script"]


def minimum_jerk(t: np.ndarray) -> np.ndarray:
    """Progress at times ``t`` in (0, 1] with zero velocity and acceleration at both ends."""
    return t**3 * (10.0 - 15.0 * t + 6.0 * t**2)


def palm_rest_pose(obj: ObjectSpec, offset: np.ndarray, centre: np.ndarray, drop: float) -> np.ndarray:
    """The object ``drop`` [m] above the palm's ``centre`` (its face, where the object lies [m]),
    its longest horizontal side along the hand (world y), shifted by ``offset`` (x, y) [m] and
    turned by a small yaw ``offset[2]`` [rad], (7,). An object longest along its own z axis (a pen,
    an egg) is laid on its side first, that axis along the hand."""
    extent = obj.mesh.bounds[1] - obj.mesh.bounds[0]
    if extent[2] > extent[:2].max():
        # A quarter turn about x: body z along world y, body y down; the yaw then turns it in place.
        yaw = offset[2]
        c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
        cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
        quat = np.array([cy * s, sy * s, sy * c, cy * c])  # (0, 0, sy, cy) * (s, 0, 0, c), x y z w
        bottom = obj.mesh.bounds[0, 1]
    else:
        yaw = (np.pi / 2 if extent[0] > extent[1] else 0.0) + offset[2]
        quat = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
        bottom = obj.mesh.bounds[0, 2]
    z = centre[2] - bottom + drop
    return np.array([centre[0] + offset[0], centre[1] + offset[1], z, *quat])


def start_script(
    kin: Kinematics,
    kinds: tuple[str, ...],
    kind: str,
    seconds: float,
    needed: set[str],
    seed: tuple[int, int],
    motion: str,
    hand: str,
) -> tuple[dict[str, int], np.random.Generator, Script]:
    """What a scripted ``motion`` of ``kind`` for ``kin``'s hand starts from, after refusing a kind
    not in ``kinds``, a length outside 6-120 s or a robot without the ``needed`` joints of
    ``hand``: each joint's index by its short name, the motion's random numbers (``seed``: the
    variant and the motions' base, plus the kind's place in ``kinds``) and a script at the
    robot's start joints."""
    if kind not in kinds:
        raise ValueError(f"{motion} kind: expected one of {kinds}, got {kind!r}")
    if not (6.0 <= seconds <= 120.0):
        raise ValueError(f"{motion} seconds: expected 6 to 120, got {seconds}")
    lay = kin.layout
    index = {name.rsplit(":", 1)[-1]: i for i, name in enumerate(lay.joint_names)}
    missing = sorted(needed - set(index))
    if missing:
        raise ValueError(f"{motion}s need {hand}'s joints; robot '{lay.name}' lacks {missing}")
    rng = np.random.default_rng([seed[0], seed[1] + kinds.index(kind)])
    return index, rng, Script(lay.default_q.copy(), lay.lower, lay.upper, profile=minimum_jerk)
