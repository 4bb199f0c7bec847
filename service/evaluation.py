"""Accuracy metrics: ADD as the paper uses it (not the symmetric ADD-S)."""

from __future__ import annotations

import numpy as np

__all__ = ["add_error", "transform_points"]


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    u, w = q[..., None, :3], q[..., None, 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Object-frame ``points`` (N, 3) at ``pose`` (..., 7) -> (..., N, 3) [m]."""
    return pose[..., None, :3] + _rotate(pose[..., 3:], points)


def add_error(points: np.ndarray, true_pose: np.ndarray, est_pose: np.ndarray) -> np.ndarray:
    """ADD: mean distance between corresponding surface ``points`` (N, 3) at the true and the
    estimated pose, (...,) [m] for poses (..., 7)."""
    diff = transform_points(true_pose, points) - transform_points(est_pose, points)
    return np.linalg.norm(diff, axis=-1).mean(-1)
