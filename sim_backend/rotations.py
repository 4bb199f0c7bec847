"""Quaternion algebra on torch tensors, batched over any leading axes.

Quaternions are (x, y, z, w), Warp's and Newton's order. One implementation for the whole
project: the tracker's sampling and estimates, forward kinematics and ADD all use it.
"""

from __future__ import annotations

import torch

__all__ = ["quat_conjugate", "quat_exp", "quat_log", "quat_multiply", "quat_rotate"]


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of (..., 4) quaternions (x, y, z, w)."""
    ax, ay, az, aw = a.unbind(-1)
    bx, by, bz, bw = b.unbind(-1)
    return torch.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        dim=-1,
    )


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    return torch.cat([-q[..., :3], q[..., 3:]], dim=-1)


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate (..., 3) vectors by (..., 4) unit quaternions."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * torch.linalg.cross(u, v, dim=-1)
    return v + w * t + torch.linalg.cross(u, t, dim=-1)


def quat_exp(omega: torch.Tensor) -> torch.Tensor:
    """Unit quaternion of the rotation vector ``omega`` (..., 3) [rad]."""
    angle = torch.linalg.vector_norm(omega, dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(x/2)/x -> 1/2 as x -> 0; the series keeps the gradient and the value exact near zero.
    scale = torch.where(angle > 1e-6, torch.sin(half) / angle.clamp_min(1e-12), 0.5 - angle * angle / 48.0)
    return torch.cat([omega * scale, torch.cos(half)], dim=-1)


def quat_log(q: torch.Tensor) -> torch.Tensor:
    """Rotation vector (..., 3) [rad] of unit quaternions (..., 4), angle in [0, pi]."""
    q = torch.where(q[..., 3:] < 0, -q, q)  # the short way round
    s = torch.linalg.vector_norm(q[..., :3], dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., 3:])
    scale = torch.where(s > 1e-7, angle / s.clamp_min(1e-12), 2.0 / q[..., 3:].clamp_min(1e-12))
    return q[..., :3] * scale
