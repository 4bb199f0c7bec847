"""What the worlds' object poses say, weighted by their costs: the estimate (the weighted mean, or
the lowest-cost world's pose), its covariance, and the two heaviest modes, where contact cannot tell
two poses apart. Torch ops inside the captured frame."""

from __future__ import annotations

import numpy as np
import torch

from inhand_tracker.sim_backend.rotations import quat_conjugate, quat_log, quat_multiply

from .config import EstimateConfig
from .optimizers import HELD_COST, OptimizerConfig, estimate_pmf
from .sampling import weighted_mean

__all__ = ["open_loop_share", "pose_modes", "pose_statistics", "unresolved_variance"]

_MISMATCH_CAP = 16.0
"""The most the floor's variance grows with the cost (4x its deviation): a population that lost its
object scores 1e9, and its region would cover the room; its status says so instead."""


def pose_modes(
    poses: torch.Tensor, best: torch.Tensor, weights: torch.Tensor, angle: float, distance: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The two heaviest pose modes of each group's worlds ``poses`` (G, K, 7) under ``weights``
    (G, K): the one around the lowest-cost world's pose ``best`` (G, 7), and the one around the
    heaviest world outside it. A mode is the worlds within ``angle`` [rad] and ``distance`` [m]
    of its seed (a quaternion and its negative are one rotation). Returns the seeds (G, 2, 7),
    the modes' shares of the weights (G, 2) and which worlds are in the first mode (G, K) bool."""

    def near(seed: torch.Tensor) -> torch.Tensor:  # (G, 7) -> (G, K) bool
        dot = (poses[..., 3:] * seed[:, None, 3:]).sum(-1).abs().clamp(max=1.0)
        close = (poses[..., :3] - seed[:, None, :3]).norm(dim=-1) < distance
        return close & (2 * torch.acos(dot) < angle)

    first = near(best)
    heaviest_away = weights.masked_fill(first, -1.0).argmax(-1)
    second_seed = poses.gather(1, heaviest_away[:, None, None].expand(-1, 1, 7))[:, 0]
    second = near(second_seed) & ~first
    shares = torch.stack([(weights * first).sum(-1), (weights * second).sum(-1)], -1)
    return torch.stack([best, second_seed], 1), shares, first


def pose_statistics(
    object_pose: torch.Tensor,
    window: torch.Tensor,
    origin: torch.Tensor,
    config: EstimateConfig,
    sharpness: torch.Tensor | None = None,
    anchor: torch.Tensor | None = None,
    reckon: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The lowest-cost world of each group, (G,), and the estimate's pose fields from every world's
    ``object_pose`` (G, K, 7) weighted by its ``window`` cost (G, K): ``pose``, ``best_pose``,
    ``mean_pose`` (G, 7), ``covariance`` (G, 6, 6), ``modes`` (G, 2, 7), ``mode_weights`` (G, 2).
    ``origin`` (7,) stands in for a NaN world's pose; ``sharpness`` (G, 1): each group's factor on
    ``estimate_lambda`` (0 weighs every held world alike). ``anchor`` (G, K) bool: each group's
    open-loop world (an OLP group's first, at sharpness 0), which the reported pose leans on by
    1 - ``sharpness`` while it holds the object (the spread, modes and ``mean_pose`` stay the
    population's), and by at least ``reckon`` (G, 1) (:func:`open_loop_share`), which makes it a
    hypothesis apart: it weighs nothing in the population's statistics, where a drifting world
    would pull the mean by its share of the weights. ``reckoning`` (G,): how far the pose is the
    open-loop world's, 0 to 1."""
    own = window  # every world's own cost, the anchor's included: does it hold the object
    if reckon is not None and anchor is not None:
        window = window.masked_fill(anchor, HELD_COST)
    best = window.argmin(-1)
    # A NaN world weighs nothing, but 0 * NaN is NaN: its pose must not reach the sums.
    poses = torch.where(torch.isfinite(object_pose).all(-1, keepdim=True), object_pose, origin)
    pose = torch.gather(poses, 1, best[:, None, None].expand(-1, 1, 7))[:, 0]
    lam = config.estimate_lambda if sharpness is None else config.estimate_lambda * sharpness
    weights = estimate_pmf(window, lam)  # (G, K)
    position = poses[..., :3]
    quat = poses[..., 3:]
    # Align every quaternion with the best one's hemisphere, then average (fine for spreads << 1 rad).
    quat = torch.where((quat * pose[:, None, 3:]).sum(-1, keepdim=True) < 0, -quat, quat)
    mean_pose = weighted_mean(weights, position, quat)
    mean_p, mean_q = mean_pose[:, :3], mean_pose[:, 3:]
    delta = torch.cat(
        [position - mean_p[:, None], quat_log(quat_multiply(quat_conjugate(mean_q)[:, None].expand_as(quat), quat))],
        dim=-1,
    )
    modes, mode_weights, first = pose_modes(poses, pose, weights, config.mode_angle, config.mode_distance)
    reported, reported_weights = mean_pose, weights
    lean = torch.zeros_like(window[:, :1])
    if config.mean_over_mode:
        # A mean across two modes (an object in the hand and one that rolled off it) lies where
        # neither is: the report takes the lowest-cost world's mode, all the worlds where they agree.
        # Where the costs say nothing of the poses (sharpness 0) the lowest is no mode's: all count.
        mode = first if sharpness is None else first | (sharpness <= 0)
        reported_weights = weights * mode / (weights * mode).sum(-1, keepdim=True)
        reported = weighted_mean(reported_weights, position, quat)
    if anchor is not None and sharpness is not None:
        # Dead reckoning as far as the costs do not tell the poses apart: where they say nothing the
        # report is the open-loop world's, not the mean of worlds spread by the priors alone.
        lean = 1.0 - sharpness if reckon is None else (1.0 - sharpness).clamp_min(reckon)
        lean = lean * (anchor & (own < HELD_COST)).any(-1, keepdim=True)
        reported = weighted_mean((1.0 - lean) * reported_weights + lean * anchor.float(), position, quat)
    return best, {
        "pose": reported if config.mean_estimate else pose,
        "best_pose": pose,
        "mean_pose": mean_pose,
        "covariance": torch.einsum("gk,gki,gkj->gij", weights, delta, delta),
        "modes": modes,
        "mode_weights": mode_weights,
        "reckoning": lean[:, 0],
    }


def open_loop_share(
    sums: torch.Tensor, window: torch.Tensor, anchor: torch.Tensor, feels: torch.Tensor, config: OptimizerConfig
) -> torch.Tensor | None:
    """How far each group reports its open-loop world, (G, 1): 1 while the ``anchor`` (1, K) world's
    window cost summed over the frames is within ``config.open_loop_ratio`` of the lowest-cost
    world's, or within ``config.min_spread`` of it (before the hand touches the object every cost is
    about 0); under ``config.until_felt``, 1 until the robot first ``feels`` (G,) bool the object;
    else 0. None while neither is on. ``sums`` (G, 3), the anchor's and the lowest since the group
    was seeded and whether it has felt the object since, gain this frame's ``window`` (G, K) in
    place. Sums, not one frame's costs, which differ by noise."""
    ratio, share = config.open_loop_ratio, None
    if ratio > 0:
        sums[:, :2].add_(torch.stack([(window * anchor).sum(-1), window.amin(-1)], -1))
        lowest = sums[:, 1:2]
        share = (sums[:, :1] <= torch.maximum(ratio * lowest, lowest + config.min_spread)).float()
    if config.until_felt:
        sums[:, 2:].copy_(torch.maximum(sums[:, 2:], feels[:, None].float()))
        unfelt = 1.0 - sums[:, 2:]
        share = unfelt if share is None else torch.maximum(share, unfelt)
    return share


def unresolved_variance(cost: np.ndarray, seeded: np.ndarray, worlds: int, config: EstimateConfig) -> np.ndarray:
    """The variance the worlds' spread does not show, (G, 6) [m^2, rad^2], added to the reported
    covariance (reported, not judged): the model's mismatch, growing with the lowest window
    ``cost`` (G,) that no world explains, and the resolution of ``worlds`` over the region each
    group was last seeded with, variances ``seeded`` (G, 6). On the host, with the estimate."""
    floor = np.array([config.covariance_floor_t**2] * 3 + [config.covariance_floor_r**2] * 3, np.float32)
    mismatch = np.clip(np.nan_to_num(cost, nan=np.inf) / config.covariance_cost_ref, 0.0, _MISMATCH_CAP)
    return floor * mismatch[:, None] + seeded * (config.covariance_resolution / worlds)
