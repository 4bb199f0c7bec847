"""Grasp planning for the procedural hand: a pinch between the thumb and the three fingers.

With the wrist angles at zero the palm faces down and the fingers point along world +x; the
fingertips close on the object from +x and the thumb from -x, so the squeeze runs along world x
and gravity is held by friction alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .kinematics import Kinematics
from .objects import ObjectSpec
from .robots import TIP_RADIUS

__all__ = ["PINCH_OFFSET", "SQUEEZE_DEPTH", "SQUEEZE_JOINTS", "Grasp", "plan_pinch"]

PINCH_OFFSET = np.array([0.045, 0.0, -0.11])
"""Where the pinch centre sits relative to the palm origin (world frame, wrist angles zero) [m]."""
_FINGER_Y = (0.03, 0.0, -0.03)
SQUEEZE_JOINTS = [7, 8, 11, 12, 15, 16, 20, 21]
"""The proximal and middle flexion joints of every digit: opening them lets go."""
SQUEEZE_DEPTH = 0.02
"""How far past touching each pad's target is pressed into the object, along the squeeze [m]."""


@dataclass(frozen=True)
class Grasp:
    """A planned pinch: where the object goes and the joint positions that hold it."""

    object_pose: np.ndarray
    """Object pose at grasp, shape (7,): position [m], quaternion (x, y, z, w)."""
    q_touch: np.ndarray
    """Joint positions with the pads just touching the object, shape (D,)."""
    q_squeeze: np.ndarray
    """Joint targets that press every pad straight into the object, shape (D,)."""


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


def plan_pinch(
    kin: Kinematics, obj: ObjectSpec, wrist_q: np.ndarray | None = None, depth: float = SQUEEZE_DEPTH
) -> Grasp:
    """Plan a pinch of ``obj`` by the hand at ``wrist_q`` (6,: x, y, z [m], then zero angles).

    The object is turned about z so its narrower horizontal side lies along the squeeze; the
    pads touch its surface at the height of its mid-length cross-section, each at its own
    place along the row; the squeeze targets put every pad ``depth`` [m] inside the object,
    straight along the squeeze.
    """
    lay = kin.layout
    q = lay.default_q.copy()
    if wrist_q is not None:
        q[:6] = wrist_q
    ext = obj.mesh.extents
    yaw = math.pi / 2 if ext[0] > ext[1] else 0.0
    c, s = math.cos(yaw), math.sin(yaw)
    verts = obj.surface_points(20000).astype(np.float64) @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    mid = verts[np.abs(verts[:, 1]) < 0.1 * np.ptp(verts[:, 1]) + 1e-3]
    # A curved object's mid cross-section lies off its centre of mass along the squeeze: the pads
    # must close on that cross-section evenly, or the side touched first pushes the object over
    # before the other arrives. (Sub-nanometre offsets are sampling rounding on symmetric shapes.)
    offset = 0.5 * float(mid[:, 0].min() + mid[:, 0].max())
    offset = offset if abs(offset) > 1e-9 else 0.0
    centre_z = float(0.5 * (mid[:, 2].min() + mid[:, 2].max()))
    centre = q[:3] + PINCH_OFFSET
    origin = centre - np.array([offset, 0.0, centre_z])  # the object's origin in the world

    def surface_x(y: float, side: float) -> float:
        """Where the object's surface lies along the squeeze at the pad's height and ``y``: each pad
        touches its own cross-section, which on a curved object is not the middle one."""
        band = verts[(np.abs(verts[:, 1] - y) < 0.004) & (np.abs(verts[:, 2] - centre_z) < 0.003)]
        return float(origin[0] + (band[:, 0].max() if side > 0 else band[:, 0].min()))

    targets = np.array(
        [[surface_x(y, 1.0) + TIP_RADIUS, centre[1] + y, centre[2]] for y in _FINGER_Y]
        + [[surface_x(0.0, -1.0) - TIP_RADIUS, centre[1], centre[2]]]
    )
    start = q.copy()
    start[[7, 11, 15]] = 0.8
    start[6 + 12] = 1.3
    active = np.zeros(lay.dof_count, bool)
    active[6:] = True
    q_touch = kin.solve_tips(start, targets, active=active)
    # Straight in, not by closing the flexion joints further: the thumb's flexion swings its tip
    # up and sideways (12 mm in, 17 mm across and 29 mm up for 0.3 rad on the spam can), and that
    # shoved the object 16-31 mm over the table before the lift (docs/benchmarks.md).
    inward = np.array([[-depth, 0.0, 0.0]] * len(_FINGER_Y) + [[depth, 0.0, 0.0]])
    q_squeeze = kin.solve_tips(q_touch, kin.sensor_poses(q_touch)[0] + inward, active=active)
    pose = np.concatenate([origin, _yaw_quat(yaw)])
    return Grasp(object_pose=pose, q_touch=q_touch, q_squeeze=q_squeeze)
