"""SE(3) and parameter noise (paper section III-D), batched over groups and worlds.

Quaternions are (x, y, z, w). Rotations are sampled as zero-mean isotropic tangent vectors in
so(3) applied to the mean rotation on the right (body frame), as in the paper's reference [36].
"""

from __future__ import annotations

import torch

from sim_backend.rotations import quat_exp, quat_multiply

__all__ = ["clipped_normal", "sample_poses", "sample_wrenches"]


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
    # Built on the device, not copied from a host list: this runs inside the captured update.
    scale = torch.where(torch.arange(6, device=device) < 3, sigma_force, sigma_torque)
    return noise * scale
