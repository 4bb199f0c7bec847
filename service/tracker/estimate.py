"""What an estimate says beyond the pose: the modes of the worlds' poses, where contact cannot
tell two poses apart."""

from __future__ import annotations

import torch

__all__ = ["pose_modes"]


def pose_modes(
    poses: torch.Tensor, best: torch.Tensor, weights: torch.Tensor, angle: float, distance: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The two heaviest pose modes of each group's worlds ``poses`` (G, K, 7) under ``weights``
    (G, K): the one around the lowest-cost world's pose ``best`` (G, 7), and the one around the
    heaviest world outside it. A mode is the worlds within ``angle`` [rad] and ``distance`` [m]
    of its seed (a quaternion and its negative are one rotation). Returns the seeds (G, 2, 7) and
    the modes' shares of the weights (G, 2)."""

    def near(seed: torch.Tensor) -> torch.Tensor:  # (G, 7) -> (G, K) bool
        dot = (poses[..., 3:] * seed[:, None, 3:]).sum(-1).abs().clamp(max=1.0)
        close = (poses[..., :3] - seed[:, None, :3]).norm(dim=-1) < distance
        return close & (2 * torch.acos(dot) < angle)

    first = near(best)
    heaviest_away = weights.masked_fill(first, -1.0).argmax(-1)
    second_seed = poses.gather(1, heaviest_away[:, None, None].expand(-1, 1, 7))[:, 0]
    second = near(second_seed) & ~first
    shares = torch.stack([(weights * first).sum(-1), (weights * second).sum(-1)], -1)
    return torch.stack([best, second_seed], 1), shares
