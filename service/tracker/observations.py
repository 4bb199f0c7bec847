"""Pose observations: a camera's estimate of the object (pose and covariance) scored against a
group's worlds. Each world's Mahalanobis distance joins the window's cost until the next update;
an observation no world agrees with re-seeds the group around it, and one the worlds agree with
less than its noise allows draws a share of them around it.

A few torch ops over one group's K worlds, outside the captured frame, on the population's stream;
the gate reads one number back, on the frames an observation arrives only."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from inhand_tracker.sim_backend.rotations import quat_conjugate, quat_log, quat_multiply

from .optimizers import HELD_COST
from .sampling import sample_poses

if TYPE_CHECKING:
    from .tracker import Tracker

__all__ = ["CHI2_6_95", "PoseObserver"]

CHI2_6_95 = 12.59
"""The 95 % quantile of the chi-squared distribution with 6 degrees of freedom (a pose)."""


class PoseObserver:
    """Pose observations for the groups of one tracker."""

    def __init__(self, tracker: Tracker):
        self.tracker = tracker
        self.config = tracker.config.observations

    def observe(self, group: int, pose: np.ndarray, covariance: np.ndarray) -> bool:
        """Score ``group``'s worlds against an observed object pose (7,) with its ``covariance``
        (6, 6; position [m^2], rotation vector [rad^2]). When no world lies within
        ``observation_gate`` of a confident observation the group is re-seeded around it instead
        (the worlds lost the object; contact alone would not bring them back); when the nearest
        lies beyond ``inject_gate``, a share of the worlds is drawn around it (:meth:`_inject`).
        Returns whether it re-seeded. An open-loop group (OLP) ignores it: it simulates its start alone."""
        t, cfg = self.tracker, self.config
        if bool(t.olp[group]):
            return False
        observed = torch.as_tensor(np.asarray(pose, np.float32), device=t.device)
        cov = torch.as_tensor(np.asarray(covariance, np.float64), device=t.device)
        chol = torch.linalg.cholesky(cov)
        d2 = self._distance(group, observed, chol)  # (K,)
        host = np.asarray(covariance, np.float64)
        largest = lambda block: float(np.sqrt(np.linalg.eigvalsh(block).max()))  # noqa: E731
        position_sigma, rotation_sigma = largest(host[:3, :3]), largest(host[3:, 3:])
        confident = position_sigma < cfg.observation_confident
        nearest = float(d2.min())
        if confident and nearest > cfg.observation_gate:
            anchor = np.tile(np.asarray(pose, np.float32), (t.G, 1))
            mask = np.zeros(t.G, bool)
            mask[group] = True
            t.seed_groups(mask, anchor, t.real.q.detach().cpu().numpy(), position_sigma, rotation_sigma)
            t.recovery.reseeded(anchor, mask)
            return True
        may_draw = cfg.inject_share > 0 and t.K > 1
        if confident and may_draw and nearest > cfg.inject_gate:
            self._inject(group, observed, position_sigma, rotation_sigma)
            d2 = self._distance(group, observed, chol)
        t.windows.evidence[group] += (cfg.observation_weight / CHI2_6_95) * d2.float()
        return False

    def _inject(self, group: int, observed: torch.Tensor, sigma_t: float, sigma_r: float) -> None:
        """Draw the least likely ``inject_share`` of ``group``'s worlds around an observed pose
        (7,) (sensor resetting, as in mixture Monte Carlo localisation). Each new world is a copy
        of the group's best, hand, velocities and physics, with its object moved: reset to the real
        joints at rest instead, a new world's hand lags the moving ones and its cost loses to theirs."""
        t = self.tracker
        scored = t.scored()[group]
        count = max(1, round(self.config.inject_share * t.K))
        worst = scored.topk(count).indices
        index = torch.arange(t.K, device=t.device).expand(t.G, t.K).clone()
        index[group, worst] = scored.argmin()
        window = t.windows.sum
        held = window[group] < HELD_COST
        typical = window[group][held].median() if bool(held.any()) else window.new_tensor(0.0)
        t.pop.resample(index)
        poses = sample_poses(observed[None], sigma_t, sigma_r, count, t.gen)[0]
        coords = t.pop.object_coords
        coords[group, worst] = poses
        drawn = torch.zeros(t.G, t.K, dtype=torch.bool, device=t.device)
        drawn[group, worst] = True
        t.pop.separate_object(drawn)
        # The new worlds join the window at its typical cost: their source's would make them the
        # best before they scored a frame.
        window[group, worst] = typical
        t.windows.evidence[group, worst] = 0.0

    def _distance(self, group: int, observed: torch.Tensor, chol: torch.Tensor) -> torch.Tensor:
        """Each of ``group``'s worlds' Mahalanobis distance squared from an observed pose (7,)
        under its covariance's Cholesky factor (6, 6), (K,); large for a NaN world."""
        poses = self.tracker.pop.object_coords[group]  # (K, 7), the state as it will step next
        q_obs = observed[3:].expand_as(poses[:, 3:])
        delta = torch.cat(
            [poses[:, :3] - observed[:3], quat_log(quat_multiply(quat_conjugate(q_obs), poses[:, 3:]))], -1
        )
        delta = torch.nan_to_num(delta.double(), nan=1e3)  # a NaN world agrees with nothing
        return torch.cholesky_solve(delta.T, chol).T.mul(delta).sum(-1)
