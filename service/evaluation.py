"""Accuracy metrics: ADD as the paper uses it, ADD-S for objects whose symmetries contact cannot
see, and whether the truth lies inside the estimate's reported uncertainty."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from inhand_tracker.sim_backend.rotations import quat_conjugate, quat_log, quat_multiply, quat_rotate

__all__ = [
    "CHI2_6DOF_95",
    "add_error",
    "adds_error",
    "catalog_add",
    "covered",
    "pose_error",
    "transform_points",
    "within_region",
]

CHI2_6DOF_95 = 12.592
"""The 95 % quantile of a chi-square with 6 degrees of freedom: the reported 95 % region's bound."""


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Object-frame ``points`` (N, 3) at ``pose`` (..., 7) -> (..., N, 3) [m]."""
    pose_t = torch.as_tensor(np.array(pose, dtype=np.float64))  # a copy: broadcast views are read-only
    points_t = torch.as_tensor(np.asarray(points, dtype=np.float64))
    q = pose_t[..., None, 3:].expand(*pose_t.shape[:-1], points_t.shape[0], 4)
    return (pose_t[..., None, :3] + quat_rotate(q, points_t.expand_as(q[..., :3]))).numpy()


def catalog_add(name: str, true_pose: np.ndarray, est_pose: np.ndarray) -> np.ndarray:
    """ADD (:func:`add_error`) of the catalog object ``name`` over its surface; a ValueError for
    an object the catalog does not hold. The replay report's scorer (``client.report.Scorer``)."""
    from inhand_tracker.sim_backend import catalog_object

    return add_error(catalog_object(name).surface_points(1000), true_pose, est_pose)


def add_error(points: np.ndarray, true_pose: np.ndarray, est_pose: np.ndarray) -> np.ndarray:
    """ADD: mean distance between corresponding surface ``points`` (N, 3) at the true and the
    estimated pose, (...,) [m] for poses (..., 7)."""
    diff = transform_points(true_pose, points) - transform_points(est_pose, points)
    return np.linalg.norm(diff, axis=-1).mean(-1)


def adds_error(points: np.ndarray, true_pose: np.ndarray, est_pose: np.ndarray) -> np.ndarray:
    """ADD-S: mean distance from each surface point at the estimated pose to the closest surface
    point at the true pose, (...,) [m] for poses (..., 7): a turned can scores as its shape looks."""
    shape = np.broadcast_shapes(np.shape(true_pose), np.shape(est_pose))[:-1]
    true = np.broadcast_to(true_pose, (*shape, 7)).reshape(-1, 7)
    est = transform_points(np.ascontiguousarray(np.broadcast_to(est_pose, (*shape, 7)).reshape(-1, 7)), points)
    # Into the true object's frame, where one tree of the points answers every pose.
    inverse = torch.tensor(true[:, 3:], dtype=torch.float64)
    local = torch.as_tensor(est - true[:, None, :3])
    local = quat_rotate(quat_conjugate(inverse)[:, None].expand(*local.shape[:2], 4), local).numpy()
    distance, _ = cKDTree(points).query(local.reshape(-1, 3))
    return distance.reshape(*shape, len(points)).mean(-1)


def pose_error(true_pose: np.ndarray, est_pose: np.ndarray) -> np.ndarray:
    """The true pose seen from the estimate, (..., 6) float64: position difference [m] and the
    rotation vector of est^-1 true [rad], as an Estimate's covariance is laid out."""
    t = torch.as_tensor(np.asarray(true_pose, np.float64))
    e = torch.as_tensor(np.asarray(est_pose, np.float64))
    e, t = torch.broadcast_tensors(e, t)
    turn = quat_log(quat_multiply(quat_conjugate(e[..., 3:]), t[..., 3:]))
    return torch.cat([t[..., :3] - e[..., :3], turn], -1).numpy()


def covered(true_pose: np.ndarray, est_pose: np.ndarray, covariance: np.ndarray, floor: float = 1e-10) -> np.ndarray:
    """Whether the true pose lies in the estimate's 95 % region: its Mahalanobis distance under
    ``covariance`` (..., 6, 6; position and rotation vector about ``est_pose``, as an Estimate's)
    within the 6-dof chi-square bound, (...,) bool. ``floor`` [m^2, rad^2] keeps a collapsed
    population's singular covariance invertible."""
    return within_region(pose_error(true_pose, est_pose), covariance, floor)


def within_region(error: np.ndarray, covariance: np.ndarray, floor: float = 1e-10) -> np.ndarray:
    """:func:`covered` for a :func:`pose_error` already at hand, (..., 6) -> (...,) bool."""
    delta = torch.as_tensor(np.asarray(error, np.float64))
    cov = torch.as_tensor(np.asarray(covariance, np.float64)) + floor * torch.eye(6, dtype=torch.float64)
    d2 = (delta[..., None, :] @ torch.linalg.solve(cov, delta[..., None]))[..., 0, 0]
    return (d2 <= CHI2_6DOF_95).numpy()
