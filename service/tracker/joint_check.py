"""The model check: how far the simulated hands' joints run from the measured ones, per group and
joint. The worlds replay the robot's commands through the config's servos; a servo that is not the
robot's (a gain off by 2x, a coupling the model lacks) shows as a joint that the worlds hold
somewhere the real one is not, whatever the object does."""

from __future__ import annotations

import torch

__all__ = ["JointCheck"]


class JointCheck:
    """An exponentially weighted mean square of (nearest simulated joint - measured joint), (G, D)
    [rad^2 or m^2], over about ``frames`` frames; updated inside the captured frame."""

    def __init__(self, groups: int, joints: int, device: torch.device, frames: float = 60.0):
        self.alpha = 1.0 / frames
        self.mean_square = torch.zeros(groups, joints, device=device)
        """(G, D) [rad^2 or m^2]."""
        self.frames = torch.zeros(groups, 1, device=device)
        """Frames seen per group since it started, (G, 1): the mean is unbiased by dividing by the
        weight its first frames had (an early mean is not a zero one)."""

    def start(self, groups: torch.Tensor) -> None:
        """Forget what ``groups`` (G,) bool saw: a new session."""
        self.mean_square.masked_fill_(groups[:, None], 0.0)
        self.frames.masked_fill_(groups[:, None], 0.0)

    def update(self, simulated: torch.Tensor, measured: torch.Tensor) -> None:
        """One frame: the worlds' joints (G, K, D) against the robot's (G, D), each joint by the world
        nearest the robot's: a finger stopped by the object stops where that world's object is, so
        worlds with the object elsewhere disagree for the object's sake; a servo that is not the
        robot's leaves every world off."""
        nearest = (simulated - measured[:, None]).abs().amin(1)
        self.mean_square.mul_(1.0 - self.alpha).add_(nearest.square(), alpha=self.alpha)
        self.frames.add_(1.0)

    def rms(self) -> torch.Tensor:
        """The RMS disagreement per group and joint, (G, D) [rad or m]."""
        weight = 1.0 - (1.0 - self.alpha) ** self.frames.clamp_min(1.0)
        return (self.mean_square / weight).sqrt()
