"""SE(3) and parameter noise (paper section III-D), batched over groups and worlds.

Quaternions are (x, y, z, w). Rotations are sampled as zero-mean isotropic tangent vectors in
so(3) applied to the mean rotation on the right (body frame), as in the paper's reference [36].
"""

from __future__ import annotations

import torch

from inhand_tracker.sim_backend.rotations import quat_conjugate, quat_exp, quat_log, quat_multiply, quat_rotate

__all__ = [
    "chance_shift",
    "clipped_normal",
    "group_mean",
    "lowest_point",
    "perturb_within",
    "recentre",
    "roughening_sigma",
    "sample_poses",
    "sample_wrenches",
    "shrink_toward_mean",
    "silverman_bandwidth",
    "weighted_mean",
]


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


def silverman_bandwidth(k: int, dim: int = 6) -> float:
    """Silverman's rule of thumb for a Gaussian kernel over ``k`` samples in ``dim`` dimensions,
    as a multiple of the samples' standard deviation: (4 / (k (dim + 2)))^(1 / (dim + 4)).
    0.645 for 40 poses, 0.41 for 4096."""
    return (4.0 / (k * (dim + 2))) ** (1.0 / (dim + 4))


def roughening_sigma(pose: torch.Tensor, bandwidth: float, floor: torch.Tensor, ceiling: torch.Tensor) -> torch.Tensor:
    """Standard deviations of a roughening displacement for each group of poses (G, K, 7),
    (G, 1, 6): translation [m], then rotation [rad].

    ``bandwidth`` times the group's spread (the RMS per axis of its positions, and of its
    rotation vectors from its first pose), at least ``floor`` (1, 1, 6) and at most ``ceiling``
    (2,): translation, rotation. Torch ops only: it runs inside the captured update."""
    g = pose.shape[0]
    quat = pose[..., 3:]
    turn = quat_log(quat_multiply(quat_conjugate(quat[:, :1]).expand_as(quat), quat))
    spread = torch.stack(
        [(x - x.mean(1, keepdim=True)).square().mean((1, 2)).sqrt() for x in (pose[..., :3], turn)], dim=-1
    )  # (G, 2)
    wide = torch.minimum(bandwidth * spread, ceiling)[..., None].expand(g, 2, 3).reshape(g, 1, 6)
    return torch.maximum(floor, wide)


def weighted_mean(weights: torch.Tensor, position: torch.Tensor, quat: torch.Tensor) -> torch.Tensor:
    """The pose (G, 7) of ``weights`` (G, K, summing to 1) over ``position`` (G, K, 3) and ``quat``
    (G, K, 4), the quaternions already in one hemisphere (fine for spreads << 1 rad)."""
    mean_q = torch.nn.functional.normalize((weights[..., None] * quat).sum(1), dim=-1)
    return torch.cat([(weights[..., None] * position).sum(1), mean_q], dim=-1)


def group_mean(pose: torch.Tensor, held: torch.Tensor | None = None) -> torch.Tensor:
    """Each group's unweighted mean pose (G, 7) of its worlds' ``pose`` (G, K, 7), over the ``held``
    (G, K) bool ones where given, the quaternions first brought into the hemisphere of the group's
    first. A NaN pose counts as not held; a group with none held gives the origin."""
    held = torch.ones_like(pose[..., 0], dtype=torch.bool) if held is None else held
    held = held & torch.isfinite(pose).all(-1)
    pose = torch.where(held[..., None], pose, torch.eye(7, device=pose.device, dtype=pose.dtype)[6])
    quat = pose[..., 3:]
    quat = torch.where((quat * quat[:, :1]).sum(-1, keepdim=True) < 0, -quat, quat)
    return weighted_mean(held / held.sum(-1, keepdim=True).clamp_min(1), pose[..., :3], quat)


def recentre(pose: torch.Tensor, target: torch.Tensor, moved: torch.Tensor, share: torch.Tensor | None = None):
    """Displacements (G, K, 6) of the ``moved`` (G, K) worlds, alike within a group, that bring the
    group's mean of ``pose`` (G, K, 7) to ``target`` (G, 7), as :meth:`Population.displace_object`
    takes them; zero in a group where none moved. ``share`` (G, 6): how far along each direction
    (translation in the world frame, rotation about the mean's axes); all the way where None. Torch
    ops only: it runs inside the captured update."""
    k = pose.shape[1]
    mean = group_mean(pose)
    goal_q = torch.where((target[:, 3:] * mean[:, 3:]).sum(-1, keepdim=True) < 0, -target[:, 3:], target[:, 3:])
    turn = quat_log(quat_multiply(quat_conjugate(mean[:, 3:]), goal_q))
    gap = torch.cat([target[:, :3] - mean[:, :3], turn], dim=-1)  # (G, 6)
    gap = gap if share is None else gap * share
    return (gap * (k / moved.sum(-1, keepdim=True).clamp_min(1)))[:, None] * moved[..., None]


def chance_shift(pose: torch.Tensor, held: torch.Tensor, sources: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """How much of a resampling's move of the worlds' mean chance alone explains: the group's mean
    pose before it (G, 7), over the ``held`` (G, K) worlds of ``pose`` (G, K, 7), and per direction
    (translation in the world frame, rotation about the mean's axes) the share of the move to undo,
    (G, 6). ``sources`` (G, K): the world each world takes its state from. A selection at random
    with the same copy counts moves the mean by a standard deviation of the worlds' spread times
    sqrt(1 / ESS - 1 / K): the move is undone where it is within one, kept from two, in proportion
    between. (Written here: resampling schemes keep the mean only in expectation, not per draw.)"""
    k = pose.shape[1]
    before = group_mean(pose, held)
    held = held & torch.isfinite(pose).all(-1)
    quat = torch.where((pose[..., 3:] * before[:, None, 3:]).sum(-1, keepdim=True) < 0, -pose[..., 3:], pose[..., 3:])
    turn = quat_log(quat_multiply(quat_conjugate(before[:, None, 3:]).expand_as(quat), quat))
    x = torch.nan_to_num(torch.cat([pose[..., :3] - before[:, None, :3], turn], dim=-1)) * held[..., None]
    n = held.sum(-1, keepdim=True).clamp_min(1)
    counts = torch.zeros_like(x[..., 0]).scatter_add_(1, sources, torch.ones_like(x[..., 0]))
    ess = k * k / counts.square().sum(-1, keepdim=True)
    chance = (x.square().sum(1) / n - (x.sum(1) / n).square()) * (1.0 / ess - 1.0 / k).clamp_min(0.0)
    moved = (counts[..., None] * x).sum(1) / k - x.sum(1) / n
    return before, (2.0 - moved.abs() / chance.sqrt().clamp_min(1e-9)).clamp(0.0, 1.0)


def shrink_toward_mean(pose: torch.Tensor, factor: float) -> torch.Tensor:
    """Displacements (G, K, 6) that move each pose of a group (G, K, 7) ``factor`` of the way to
    the group's mean: translation [m] in the world frame, then rotation vector [rad] in the
    object's frame (as :meth:`Population.displace_object` takes them). The mean rotation is taken
    about the group's first pose, fine for spreads well under a radian. Torch ops only."""
    quat = pose[..., 3:]
    first = quat[:, :1].expand_as(quat)
    turn = quat_log(quat_multiply(quat_conjugate(first), quat))
    mean_q = quat_multiply(quat[:, :1], quat_exp(turn.mean(1, keepdim=True)))
    towards = quat_log(quat_multiply(quat_conjugate(quat), mean_q.expand_as(quat)))
    return factor * torch.cat([pose[..., :3].mean(1, keepdim=True) - pose[..., :3], towards], dim=-1)


def perturb_within(
    value: torch.Tensor, sigma: torch.Tensor, bounds: tuple[float, float], mask: torch.Tensor, gen: torch.Generator
) -> torch.Tensor:
    """theta ~ N(theta, Sigma_theta) clipped to its range ``bounds``, where ``mask``; ``sigma`` is a
    fraction of the range."""
    lo, hi = bounds
    return torch.where(mask, clipped_normal(value.clone(), sigma * (hi - lo), lo, hi, gen), value)


def lowest_point(quat: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Height of the lowest of ``vertices`` (V, 3) rotated by ``quat`` (..., 4), shape (...)."""
    shape = (*quat.shape[:-1], len(vertices))
    return quat_rotate(quat[..., None, :].expand(*shape, 4), vertices.expand(*shape, 3))[..., 2].amin(-1)
