"""The recovery policy: each group's track state from its estimate, and when and where to re-seed.

A group whose worlds nearly all lost the object, or whose best world disagrees with the real robot
about contact for several frames, is re-seeded around its last trusted estimate (the last one
whose best world felt the contacts the real hand felt; moved with the real hand since, if the
hand held the object then) with wider noise. When the real fingers touch nothing at that moment
the object fell, and the hypotheses are laid on the table below that estimate instead (unless the
hand carries objects on its palm, where untouched fingertips say nothing).

Host-side numpy over (G,) arrays: it reads the estimate the frame already copied back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inhand_tracker.protocol import TrackState

from .config import TrackerConfig
from .layout import GroupEstimates

__all__ = ["Recovery", "Reseed", "point_spread"]


@dataclass
class Reseed:
    """Groups to sample afresh: around ``anchor`` (G, 7) with the given noise, or on the table."""

    groups: np.ndarray
    """(G,) bool."""
    anchor: np.ndarray
    """(G, 7) pose per group [m, quaternion (x, y, z, w)]."""
    sigma_t: float
    """[m]"""
    sigma_r: float
    """[rad]"""
    on_table: bool = False


def point_spread(covariance: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """RMS displacement [m] of an object's surface points under a pose covariance (..., 6, 6)
    (position [m^2], rotation vector [rad^2]), for points whose second moment about the object's
    origin is ``moment`` (3, 3) [m^2]: E|dp + dr x x|^2 = tr(S_p) + tr(S_r) tr(M) - tr(S_r M) to
    first order, (...,). The spread in ADD terms: a turn counts by how far it moves the object."""
    rotation = covariance[..., 3:, 3:]
    turned = np.trace(rotation, axis1=-2, axis2=-1) * np.trace(moment) - np.einsum("...ij,ji->...", rotation, moment)
    return np.sqrt(np.maximum(np.trace(covariance[..., :3, :3], axis1=-2, axis2=-1) + turned, 0.0))


class Recovery:
    """Track state and the divergence rules of ``config`` for G groups of L sensors, tracking an
    object whose surface points have the second moment ``moment`` (3, 3) [m^2] about its origin.
    ``falls``: fingertips that touch nothing mean the object fell (not for a hand that carries
    objects on its palm)."""

    def __init__(self, config: TrackerConfig, groups: int, sensors: int, moment: np.ndarray, falls: bool = True):
        self.config, self.G, self.L, self.falls = config, groups, sensors, falls
        self.moment = np.asarray(moment, np.float64)
        self.status = np.zeros(groups, dtype=np.int64)
        """Track state per group, (G,) (:class:`protocol.TrackState`)."""
        self._recovering = np.zeros(groups, dtype=np.int64)
        self._contact_loss = np.zeros(groups, dtype=np.int64)
        self.trusted: np.ndarray | None = None
        """Best pose at the last trusted frame (tracking, or with a best world that agrees with the
        real hand on every sensor), (G, 7): where a diverged group is re-seeded."""
        self._trusted_hand = np.zeros((groups, 3), np.float32)
        """The real hand's position (the mean of its sensor positions) at the last trusted frame, (G, 3) [m]."""
        self._trusted_held = np.zeros(groups, bool)
        """Whether the real hand touched the object at the last trusted frame, (G,)."""
        self._cost_level = np.full(groups, np.nan)
        """The best world's window cost, averaged over the last ``surprise_frames``, (G,); NaN
        before a group's first frame."""
        self.open_loop = np.zeros(groups, bool)
        """Groups that run open loop (OLP, the paper's baseline), (G,) bool: their state is judged
        like any other's, but they are never re-seeded."""

    def start(self, p0: np.ndarray, mask: np.ndarray) -> None:
        """Groups ``mask`` (G,) start tracking from ``p0`` (G, 7)."""
        if self.trusted is None:
            self.trusted = p0.copy()
        self.trusted[mask] = p0[mask]
        self._trusted_held[mask] = False
        self.status[mask] = TrackState.TRACKING
        self._recovering[mask] = 0
        self._contact_loss[mask] = 0
        self._cost_level[mask] = np.nan

    def reseeded(self, anchor: np.ndarray, mask: np.ndarray) -> None:
        """Groups ``mask`` (G,) were re-seeded around ``anchor`` (G, 7) from a pose observation."""
        self.trusted[mask] = anchor[mask]
        self._trusted_held[mask] = False
        self.status[mask] = TrackState.RECOVERING
        self._recovering[mask] = self.config.recovery.recover_frames
        self._contact_loss[mask] = 0

    def watch(
        self,
        est: GroupEstimates,
        force: np.ndarray | None,
        felt: np.ndarray,
        hand: np.ndarray,
        touch: np.ndarray | None = None,
        felt_touch: np.ndarray | None = None,
    ) -> list[Reseed]:
        """Update the state from the estimate just copied back and say which groups to re-seed.
        ``force``: the real fingertip forces this frame, (G, L, 3) [N], or None; ``felt``: which
        groups' robots sense force, (G,) bool; ``hand``: the real hand's position, (G, 3) [m];
        ``touch``: the real touch zones' normal forces, (G, Z) [N], or None, and ``felt_touch``
        which groups' robots sent them. The object fell only where the robot senses touch and no
        sensor of it, fingertip or zone (a palm, a phalanx), feels the object."""
        cfg = self.config
        self._recovering = np.maximum(self._recovering - 1, 0)
        recovering = self._recovering > 0
        lost_contact = ~recovering & (est.contact_disagreement >= 0.5 * self.L)
        self._contact_loss = np.where(lost_contact, self._contact_loss + 1, 0)
        diverged = (est.lost > cfg.recovery.lost_fraction) | (self._contact_loss >= cfg.recovery.contact_loss_frames)
        spread = point_spread(est.covariance, self.moment)
        unsure = spread > cfg.recovery.uncertain_spread
        ambiguous = est.mode_weights[:, 1] >= cfg.recovery.ambiguous_weight
        status = np.where(unsure | self._surprised(est.cost), TrackState.UNCERTAIN, TrackState.TRACKING)
        status = np.where(ambiguous, TrackState.AMBIGUOUS, status)
        status = np.where(recovering, TrackState.RECOVERING, status)
        status = np.where(diverged, TrackState.DIVERGED, status)
        touching = np.zeros(self.G, bool)
        if force is not None:
            touching = felt & (np.linalg.norm(force, axis=-1) > cfg.cost.contact_threshold).any(-1)
        if touch is not None and felt_touch is not None:
            touching |= felt_touch & (touch > cfg.cost.contact_threshold).any(-1)
            felt = felt | felt_touch
        # The re-seed anchor is the best pose of the last frame on which the best world felt what
        # the real hand felt. A tracking frame whose best world already misses the real contacts
        # does not count: the contact-loss rule takes a few frames to call the divergence, and
        # those frames' pose (the object knocked out of every simulated hand) made the anchor. An
        # uncertain frame whose best world agrees on every sensor does count: a grasp that only
        # a few worlds made is uncertain until the lift, and anchoring before it put the
        # hypotheses back on the table under the lifted object. A surprise in the cost alone
        # (a sudden slip) does not hold the anchor back: the contacts' agreement says more.
        tracking = ~(unsure | ambiguous | recovering | diverged | lost_contact)
        trusted = tracking | (~diverged & (est.contact_disagreement == 0))
        # The mean over every world, not the report's one mode: re-seeded around a mode the worlds
        # split into, the population followed it off the hand where the mean of all had held it.
        anchor = est.mean_pose if cfg.estimate.mean_estimate else est.pose
        self.trusted[trusted] = anchor[trusted]
        self._trusted_hand[trusted] = hand[trusted]
        self._trusted_held[trusted] = touching[trusted]
        # The real fingers touch nothing while the worlds still hold the object: it fell (or was let
        # go with the worlds' object stuck). Around the last in-hand pose the closed simulated hand
        # would catch it again, so those hypotheses go onto the table below it.
        reseeds = diverged & ~self.open_loop
        dropped = reseeds & felt & ~touching & self.falls
        held = reseeds & ~dropped
        sigma_r = cfg.seeding.sigma_r * cfg.recovery.reseed_scale
        out = []
        if held.any():
            # An object held when last trusted went where the hand went since. Re-seeding at the
            # old place in the world put the hypotheses inside the lifted fingers, where they burst
            # out, were lost and re-seeded there again, frame after frame.
            anchor = self.trusted.copy()
            anchor[:, :3] += self._trusted_held[:, None] * (hand - self._trusted_hand)
            out.append(Reseed(held, anchor, cfg.seeding.sigma_t * cfg.recovery.reseed_scale, sigma_r))
        if dropped.any():
            out.append(Reseed(dropped, self.trusted, cfg.recovery.drop_sigma_t, sigma_r, on_table=True))
        if reseeds.any():
            self._recovering[reseeds] = cfg.recovery.recover_frames
            self._contact_loss[reseeds] = 0
        self.status[:] = status
        return out

    def _surprised(self, cost: np.ndarray) -> np.ndarray:
        """Whether each group's best window cost ``cost`` (G,) jumped above its recent level
        (:attr:`TrackerConfig.surprise_ratio`), (G,) bool; then folds it into that level."""
        cfg = self.config
        fresh = np.isnan(self._cost_level)
        level = np.where(fresh, cost, self._cost_level)
        surprised = (
            (cfg.recovery.surprise_ratio > 0)
            & (cost > cfg.recovery.surprise_ratio * level)
            & (cost > cfg.recovery.surprise_cost)
        )
        # A group whose worlds all lost the object scores inf: the lost-fraction rule's case, and
        # no level to learn.
        self._cost_level = np.where(
            np.isfinite(cost), level + (cost - level) / cfg.recovery.surprise_frames, self._cost_level
        )
        return surprised & ~fresh
