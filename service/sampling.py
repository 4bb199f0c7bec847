"""SE(3) and parameter noise (paper section III-D), batched over groups and worlds.

Quaternions are (x, y, z, w). Rotations are sampled as zero-mean isotropic tangent vectors in
so(3) applied to the mean rotation on the right (body frame), as in the paper's reference [36].
"""

from __future__ import annotations

import torch

__all__ = [
    "clipped_normal",
    "quat_conjugate",
    "quat_exp",
    "quat_log",
    "quat_multiply",
    "quat_rotate",
    "sample_poses",
    "sample_wrenches",
]


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


def sample_poses(
    mean: torch.Tensor, sigma_t: torch.Tensor | float, sigma_r: torch.Tensor | float, k: int, gen: torch.Generator
) -> torch.Tensor:
    """K poses per group around ``mean`` (G, 7): translation ~ N(0, sigma_t^2 I) [m], rotation =
    mean * exp(omega) with omega ~ N(0, sigma_r^2 I) [rad]. sigma_*: scalars or (G,). Returns (G, K, 7)."""
    g = mean.shape[0]
    dev, dt = mean.device, mean.dtype
    st = torch.as_tensor(sigma_t, dtype=dt, device=dev).reshape(-1, 1, 1)
    sr = torch.as_tensor(sigma_r, dtype=dt, device=dev).reshape(-1, 1, 1)
    noise = torch.randn((g, k, 6), generator=gen, device=dev, dtype=dt)
    pos = mean[:, None, :3] + st * noise[..., :3]
    rot = quat_multiply(mean[:, None, 3:].expand(g, k, 4), quat_exp(sr * noise[..., 3:]))
    return torch.cat([pos, rot], dim=-1)


def clipped_normal(
    mean: torch.Tensor, sigma: torch.Tensor | float, low: float, high: float, gen: torch.Generator
) -> torch.Tensor:
    """mean + N(0, sigma^2), clipped to [low, high]; same shape as ``mean``."""
    noise = torch.randn(mean.shape, generator=gen, device=mean.device, dtype=mean.dtype)
    return (mean + sigma * noise).clamp_(low, high)


def sample_wrenches(
    shape: tuple[int, int], sigma_force: float, sigma_torque: float, gen: torch.Generator, device: torch.device
) -> torch.Tensor:
    """Perturbation wrenches v ~ N(0, diag(sigma_force^2 I3, sigma_torque^2 I3)), (G, K, 6) [N, N m]."""
    noise = torch.randn((*shape, 6), generator=gen, device=device)
    scale = torch.tensor([sigma_force] * 3 + [sigma_torque] * 3, device=device)
    return noise * scale
