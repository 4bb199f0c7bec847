"""How far the window's costs tell a group's worlds apart beyond noise, and how far their poses
explain them beyond their physics: the evidence an update is as strong as (``by_evidence``), and
what the best world leaves unexplained of each sensing. Torch ops inside the captured update."""

from __future__ import annotations

import torch

from inhand_tracker.sim_backend.robot_specs import SensorNoise
from inhand_tracker.sim_backend.rotations import quat_conjugate, quat_log, quat_multiply

from .cost import Cost
from .optimizers import HELD_COST, OptimizerConfig

__all__ = [
    "Residuals",
    "declared_scatter",
    "evidence_strength",
    "f_bound",
    "noise_bound",
    "pose_evidence",
    "pose_sources",
    "pose_strength",
    "separation",
]


def separation(
    mean: torch.Tensor, scatter: torch.Tensor, frames: torch.Tensor, floor: torch.Tensor | float = 0.0
) -> torch.Tensor:
    """How far a window's costs separate the worlds, per group, (G,): the variance of the worlds'
    window means ``mean`` (G, K) over the mean squared standard error of each, from ``scatter``
    (G, K), each world's mean squared deviation from its group's per-frame mean cost over the
    window's ``frames`` (G,), and at least ``floor`` (G,) or one number: the scatter the robot's
    declared sensor noise can make. A one-way analysis of variance's F ratio, frames as the
    replicates: about 1 where worlds differ only by noise (more where the noise is correlated from
    frame to frame), large where some world explains the robot better and stays so. Lost worlds
    (cost from :data:`HELD_COST` up) are left out; a group with fewer than two held worlds gives 0."""
    held = mean < HELD_COST
    n = held.sum(-1).clamp_min(1)
    centre = torch.where(held, mean, 0.0).sum(-1, keepdim=True) / n[:, None]
    offset = torch.where(held, mean - centre, 0.0)
    between = offset.square().sum(-1) / (n - 1).clamp_min(1)
    # The deviations' own mean is the world's offset from the group: what is left is its scatter.
    within = torch.where(held, (scatter - offset.square()).clamp_min(0.0), 0.0).sum(-1) / n
    within = torch.maximum(within, torch.as_tensor(floor, dtype=within.dtype, device=within.device))
    f = between / (within / frames.clamp_min(1)).clamp_min(1e-12)
    return torch.where(held.sum(-1) >= 2, f, 0.0)


def noise_bound(worlds: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """The F ratio of :func:`separation` that noise alone stays below in about 95 % of windows, for
    ``worlds`` (G,) held worlds scored over ``frames`` (G,): :func:`f_bound` of K - 1 and K (n - 1)
    degrees of freedom. About 1.8 for 12 worlds over 5 frames, 1.4 for 40 over 15, 1.08 for 1024."""
    k, n = worlds.clamp_min(2), frames.clamp_min(2)
    return f_bound(k - 1, k * (n - 1))


def f_bound(d1: torch.Tensor | float, d2: torch.Tensor) -> torch.Tensor:
    """About the 95th percentile of an F ratio of ``d1`` and ``d2`` degrees of freedom under its null:
    1 + 1.645 of its standard deviations, sqrt(2 / d1 + 2 / d2) for large d2 (the normal
    approximation: the quantile itself has no closed form, and this is torch ops a graph can hold)."""
    return 1.0 + 1.645 * (2.0 / d1 + 2.0 / d2.clamp_min(1)).sqrt()


def pose_strength(cost: torch.Tensor, pose: torch.Tensor, params: torch.Tensor, epsilon: float) -> torch.Tensor:
    """How strongly the worlds' object poses (G, K, 7) may be resampled, (G, 1) in [0, 1]: the
    information in :func:`pose_evidence`'s F ratio, how far they explain the window costs ``cost``
    (G, K) beyond the physics ``params`` (G, K, P), against what noise alone gives it
    (:func:`evidence_strength`). Costs that rank the worlds by mass alone (an object lying on a palm,
    felt through its weight) give poses no strength."""
    f = pose_evidence(cost, pose, params)
    extra, reduced = 12, 2 * params.shape[-1]  # quadratics in the pose (6 and their squares), in the params
    dof = ((cost < HELD_COST) & torch.isfinite(pose).all(-1)).sum(-1) - extra - reduced - 1
    return evidence_strength(f, f_bound(float(extra), dof.float()), epsilon)


def evidence_strength(separated: torch.Tensor, bound: torch.Tensor, epsilon: float) -> torch.Tensor:
    """How strongly to update each group, (G, 1) in [0, 1], from its separation F ratio (G,): the
    information its window holds about which worlds are better, 1/2 ln(F / ``bound``) nats (the
    Gaussian channel's, with F - 1 the signal-to-noise ratio, counted from what noise alone gives:
    ``bound`` (G,), :func:`noise_bound`), as a share of the KL ``epsilon`` a full update moves the
    worlds by (REPS's bound). 0 where noise explains the differences, 1 from ``bound`` e^(2 epsilon) up."""
    information = 0.5 * torch.log(separated.clamp_min(1e-12) / bound)
    # NaN (no F ratio could be formed) is no evidence: a NaN strength would poison the estimate's weights.
    return torch.nan_to_num(information / epsilon, nan=0.0).clamp(0.0, 1.0)[:, None]


def _quadratic(x: torch.Tensor) -> torch.Tensor:
    """Each column of ``x`` (G, K, N) and its square, standardised per group, (G, K, 2N)."""
    x = torch.cat([x, x.square()], dim=-1)
    x = x - x.mean(1, keepdim=True)
    # The population's spread (no Bessel correction): the F ratio does not depend on the columns'
    # scale, and a group of one world gives zeros, not a NaN.
    return x / x.std(1, keepdim=True, correction=0).clamp_min(1e-9)


def _residual(design: torch.Tensor, y: torch.Tensor, held: torch.Tensor) -> torch.Tensor:
    """Sum of squared residuals of the least-squares fit of ``y`` (G, K) on ``design`` (G, K, N)
    plus a constant, over the ``held`` (G, K) worlds, (G,). The normal equations, with a small
    ridge, are solved by conjugate gradients written out in batched products: exact after N + 1
    steps, and unlike the solvers of torch.linalg certain to run inside a captured graph."""
    x = torch.cat([torch.ones_like(design[..., :1]), design], dim=-1) * held[..., None]
    gram = x.transpose(1, 2) @ x + 1e-6 * torch.eye(x.shape[-1], device=x.device)
    rhs = x.transpose(1, 2) @ (y * held)[..., None]
    beta = torch.zeros_like(rhs)
    r, p = rhs.clone(), rhs.clone()
    rr = r.square().sum(1, keepdim=True)
    for _ in range(2 * x.shape[-1]):  # twice the exact count: float32 rounding
        gp = gram @ p
        alpha = rr / (p * gp).sum(1, keepdim=True).clamp_min(1e-30)
        beta, r = beta + alpha * p, r - alpha * gp
        rr_next = r.square().sum(1, keepdim=True)
        p, rr = r + (rr_next / rr.clamp_min(1e-30)) * p, rr_next
    return ((x @ beta)[..., 0] - y * held).square().sum(-1)


def pose_evidence(cost: torch.Tensor, pose: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
    """How much the worlds' object poses (G, K, 7) explain their window costs ``cost`` (G, K) beyond
    their physics parameters ``params`` (G, K, P), per group, (G,): the F ratio of a nested
    least-squares fit of the costs on a quadratic in the parameters, against one that adds a
    quadratic in the poses (position, and rotation vector from the group's first world). About 1
    where the costs do not depend on the pose, large where they do (a bowl around the poses the
    robot's sensing favours). Lost worlds (cost from :data:`HELD_COST` up) are left out; a group with
    too few held worlds for the fit gives inf, so that it resamples as it would without the test."""
    # A world gone NaN neither holds nor enters the fit: one NaN would make every sum NaN.
    finite = torch.isfinite(pose).all(-1, keepdim=True)
    held = ((cost < HELD_COST) & finite[..., 0]).float()
    pose = torch.where(finite, pose, torch.eye(7, device=pose.device, dtype=pose.dtype)[6])
    quat = pose[..., 3:]
    turn = quat_log(quat_multiply(quat_conjugate(quat[:, :1]).expand_as(quat), quat))
    reduced = _quadratic(params)
    full = torch.cat([reduced, _quadratic(torch.cat([pose[..., :3], turn], dim=-1))], dim=-1)
    y = torch.where(held > 0, cost, 0.0)
    y = (y - (y * held).sum(-1, keepdim=True) / held.sum(-1, keepdim=True).clamp_min(1)) * held
    rss_reduced, rss_full = _residual(reduced, y, held), _residual(full, y, held)
    extra = full.shape[-1] - reduced.shape[-1]
    dof = held.sum(-1) - full.shape[-1] - 1
    f = ((rss_reduced - rss_full) / extra) / (rss_full / dof.clamp_min(1)).clamp_min(1e-12)
    return torch.where(dof >= 4, f, torch.inf)


def pose_sources(
    index: torch.Tensor,
    cost: torch.Tensor,
    pose: torch.Tensor,
    params: torch.Tensor,
    config: OptimizerConfig,
    strength: torch.Tensor | None = None,
    gen: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where each world's state comes from in an update whose worlds take their parameters from
    ``index`` (G, K), from the worlds' object poses (G, K, 7), window costs ``cost`` (G, K) and
    physics ``params`` (G, K, P). With an update ``strength`` (G, 1) (``by_evidence``) a replaced
    world takes its source's state as often as the poses explain the costs beyond the physics
    (:func:`pose_strength`, at most ``strength``; drawn from ``gen``); else, under
    ``config.min_pose_evidence``, every world of a group whose poses explain them over that F ratio
    does (:func:`pose_evidence`); else all. A world that lost its object always does; the others
    keep their own. Returns the sources (G, K), which worlds take their state from ``index`` (G, K)
    bool, and that share per group (G, 1): the estimate weighs the worlds' poses by it."""
    own = torch.arange(cost.shape[-1], device=cost.device).expand_as(index)
    lost = cost >= HELD_COST
    if strength is not None:
        chance = torch.minimum(pose_strength(cost, pose, params, config.reps_epsilon), strength)
        posed = (torch.rand(index.shape, generator=gen, device=index.device) < chance) | lost
    elif config.min_pose_evidence > 0:
        posed = (pose_evidence(cost, pose, params) > config.min_pose_evidence)[:, None] | lost
        # Costs that rank the worlds by their physics say nothing of their poses: weigh them alike.
        chance = posed.all(-1, keepdim=True).float()
    else:
        posed, chance = torch.ones_like(lost), torch.ones_like(cost[:, :1])
    return torch.where(posed, index, own), posed, chance


_BEYOND_TWO_SIGMA = 0.0115
"""E[(|n| - 2 sigma)+^2] / sigma^2 for Gaussian noise n: 2 ((1 + 4) Q(2) - 2 phi(2)), Q the normal's upper tail."""


def declared_scatter(cost: Cost, robot: SensorNoise, sensors: int, zones: int) -> torch.Tensor:
    """The per-frame scatter of a world's ``cost`` that ``robot``'s declared sensor noise can make,
    (G,): each term's weight times how far that noise moves what it reads, squared, summed over the
    joints, the ``sensors`` fingertips' force magnitudes and contact flags, and the ``zones`` touch
    zones' forces. A bound, not a model: where noise moves a reading by sigma, no world's term moves
    by more, and a flag flips at most once; a touch zone's force term, which counts only errors
    beyond twice the noise, moves by what the noise adds beyond that."""
    w, threshold = cost.weights(), cost.config.contact_threshold
    flips = lambda sigma: min(1.0, sigma / threshold)  # noqa: E731 - a flag's share of frames flipped, at most
    joints = (w[:, 0] * robot.joint_noise).square()
    forces = (w[:, 4] * robot.force_noise).square() + (w[:, 3] * flips(robot.force_noise)).square()
    # A zone's force error counts only beyond twice the noise (:func:`.cost.cost_terms`): noise moves
    # it by what it adds beyond that, E[(|n| - 2 sigma)+^2] = 0.0115 sigma^2 for Gaussian noise. Its
    # contact flag flips only where a zone is pressed within the noise of the contact threshold (an
    # untouched zone reads 0 under the deadband): a share no declared figure bounds, and bounding it
    # by sigma / threshold on every zone would call any two worlds alike.
    touch = (w[:, 11] * robot.touch_noise).square() * _BEYOND_TWO_SIGMA
    return joints + sensors * forces + zones * touch


class Residuals:
    """What each group's lowest-cost world leaves unexplained of each sensing, a running mean over
    about a second: state with a leading group axis, updated inside the captured frame."""

    TERMS = (0, 4, 11)
    """The cost terms read (:data:`.cost.TERM_NAMES`): joints, fingertip force magnitudes, touch zone forces."""

    def __init__(self, groups: int, joints: int, sensors: int, zones: int, device: torch.device) -> None:
        self.mean = torch.zeros(groups, 3, device=device)
        """(G, 3): joints (RMS per joint) [rad or m], each fingertip force's magnitude [N], each touch
        zone's force beyond twice the declared noise [N]; 0 where the robot sends none
        (:attr:`.layout.GroupEstimates.residual`)."""
        self.frames = torch.zeros(groups, 1, device=device)
        """Frames each group's mean has seen, (G, 1)."""
        self._per = torch.tensor([max(joints, 1) ** 0.5, max(sensors, 1), max(zones, 1)], device=device)
        self._terms = torch.tensor(self.TERMS, device=device)

    def add(self, terms: torch.Tensor, best: torch.Tensor) -> None:
        """One frame's unweighted cost ``terms`` (G, K, 12), read at each group's ``best`` (G,) world."""
        at_best = terms.gather(1, best[:, None, None].expand(-1, 1, terms.shape[-1]))[:, 0]
        self.frames += 1
        rate = (1.0 / self.frames).clamp_min(1.0 / 30.0)
        self.mean.lerp_(at_best.index_select(-1, self._terms) / self._per, rate)

    def start(self, groups: torch.Tensor) -> None:
        """Forget the means of ``groups`` (G,) bool: a new track starts there."""
        self.frames.masked_fill_(groups[:, None], 0.0)
