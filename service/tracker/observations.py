"""Pose observations: a camera's estimate of the object (pose and covariance) scored against a
group's worlds. Each world's Mahalanobis distance joins the window's cost until the next update;
an observation no world agrees with re-seeds the group around it, and one the worlds agree with
less than its noise allows draws a share of them around it.

A few torch ops over one group's K worlds, outside the captured frame, on the population's stream;
the gate reads one number back, on the frames an observation arrives only."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from inhand_tracker.sim_backend import Population
from inhand_tracker.sim_backend.rotations import quat_conjugate, quat_log, quat_multiply

from .config import ObservationConfig
from .optimizers import HELD_COST
from .sampling import sample_poses
from .window import CostWindow

__all__ = ["CHI2_6_95", "Judgement", "PoseObserver", "draw_around"]

CHI2_6_95 = 12.59
"""The 95 % quantile of the chi-squared distribution with 6 degrees of freedom (a pose)."""


@dataclass(frozen=True)
class Judgement:
    """What one observation asks of its group; the tracker applies it (:meth:`.Tracker.observe`)."""

    distance: torch.Tensor
    """Each world's Mahalanobis distance squared from the observed pose, (K,)."""
    reseed: bool
    """No world lies within the gate of a confident observation: re-seed the group around it."""
    inject: int
    """How many of the least likely worlds to draw around it (0: none)."""
    position_sigma: float
    """The observation's largest position standard deviation [m]."""
    rotation_sigma: float
    """Its largest rotation standard deviation [rad]."""


class PoseObserver:
    """Judges pose observations against a group's worlds (:meth:`judge`)."""

    def __init__(self, config: ObservationConfig, worlds: int):
        self.config = config
        self.K = worlds

    def judge(self, poses: torch.Tensor, pose: np.ndarray, covariance: np.ndarray) -> Judgement:
        """How a group whose worlds' object poses are ``poses`` (K, 7) meets an observed object
        pose (7,) with its ``covariance`` (6, 6; position [m^2], rotation vector [rad^2]). When no
        world lies within ``observation_gate`` of a confident observation the group is to be
        re-seeded around it (the worlds lost the object; contact alone would not bring them back);
        when the nearest lies beyond ``inject_gate``, a share of the worlds drawn around it."""
        cfg = self.config
        chol = self.factor(covariance, poses.device)
        d2 = self.distance(poses, self.observed(pose, poses.device), chol)
        host = np.asarray(covariance, np.float64)
        largest = lambda block: float(np.sqrt(np.linalg.eigvalsh(block).max()))  # noqa: E731
        position_sigma, rotation_sigma = largest(host[:3, :3]), largest(host[3:, 3:])
        confident = position_sigma < cfg.observation_confident
        nearest = float(d2.min())
        reseed = confident and nearest > cfg.observation_gate
        may_draw = cfg.inject_share > 0 and self.K > 1
        inject = confident and may_draw and not reseed and nearest > cfg.inject_gate
        count = max(1, round(cfg.inject_share * self.K)) if inject else 0
        return Judgement(d2, reseed, count, position_sigma, rotation_sigma)

    def evidence(self, distance: torch.Tensor) -> torch.Tensor:
        """What an observation adds to each world's window cost, (K,), from its ``distance``."""
        return (self.config.observation_weight / CHI2_6_95) * distance.float()

    @staticmethod
    def observed(pose: np.ndarray, device: torch.device) -> torch.Tensor:
        """The observed pose (7,) on ``device``."""
        return torch.as_tensor(np.asarray(pose, np.float32), device=device)

    @staticmethod
    def factor(covariance: np.ndarray, device: torch.device) -> torch.Tensor:
        """The covariance's Cholesky factor (6, 6), float64 on ``device``."""
        return torch.linalg.cholesky(torch.as_tensor(np.asarray(covariance, np.float64), device=device))

    @staticmethod
    def distance(poses: torch.Tensor, observed: torch.Tensor, chol: torch.Tensor) -> torch.Tensor:
        """Each world's Mahalanobis distance squared from an observed pose (7,) under its
        covariance's Cholesky factor (6, 6), (K,) for ``poses`` (K, 7); large for a NaN world."""
        q_obs = observed[3:].expand_as(poses[:, 3:])
        delta = torch.cat(
            [poses[:, :3] - observed[:3], quat_log(quat_multiply(quat_conjugate(q_obs), poses[:, 3:]))], -1
        )
        delta = torch.nan_to_num(delta.double(), nan=1e3)  # a NaN world agrees with nothing
        return torch.cholesky_solve(delta.T, chol).T.mul(delta).sum(-1)


def draw_around(
    pop: Population,
    windows: CostWindow,
    scored: torch.Tensor,
    group: int,
    observed: torch.Tensor,
    judged: Judgement,
    gen: torch.Generator,
) -> None:
    """Draw the least likely ``judged.inject`` of ``group``'s worlds (by ``scored`` (K,), their
    window cost) around an observed pose (7,) (sensor resetting, as in mixture Monte Carlo
    localisation). Each new world is a copy of the group's best, hand, velocities and physics, with
    its object moved: reset to the real joints at rest instead, a new world's hand lags the moving
    ones and its cost loses to theirs."""
    G, K = pop.G, pop.K
    worst = scored.topk(judged.inject).indices
    index = torch.arange(K, device=scored.device).expand(G, K).clone()
    index[group, worst] = scored.argmin()
    window = windows.sum
    held = window[group] < HELD_COST
    typical = window[group][held].median() if bool(held.any()) else window.new_tensor(0.0)
    pop.resample(index)
    poses = sample_poses(observed[None], judged.position_sigma, judged.rotation_sigma, judged.inject, gen)[0]
    coords = pop.object_coords
    coords[group, worst] = poses
    drawn = torch.zeros(G, K, dtype=torch.bool, device=scored.device)
    drawn[group, worst] = True
    pop.separate_object(drawn)
    # The new worlds join the window at its typical cost: their source's would make them the
    # best before they scored a frame.
    window[group, worst] = typical
    windows.evidence[group, worst] = 0.0
