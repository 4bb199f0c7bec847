"""Accuracy metrics: ADD as the paper uses it (not the symmetric ADD-S)."""

from __future__ import annotations

import numpy as np
import torch

from sim_backend.rotations import quat_rotate

__all__ = ["add_error", "transform_points"]


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Object-frame ``points`` (N, 3) at ``pose`` (..., 7) -> (..., N, 3) [m]."""
    pose_t = torch.as_tensor(np.asarray(pose, dtype=np.float64))
    points_t = torch.as_tensor(np.asarray(points, dtype=np.float64))
    q = pose_t[..., None, 3:].expand(*pose_t.shape[:-1], points_t.shape[0], 4)
    return (pose_t[..., None, :3] + quat_rotate(q, points_t.expand_as(q[..., :3]))).numpy()


def add_error(points: np.ndarray, true_pose: np.ndarray, est_pose: np.ndarray) -> np.ndarray:
    """ADD: mean distance between corresponding surface ``points`` (N, 3) at the true and the
    estimated pose, (...,) [m] for poses (..., 7)."""
    diff = transform_points(true_pose, points) - transform_points(est_pose, points)
    return np.linalg.norm(diff, axis=-1).mean(-1)
