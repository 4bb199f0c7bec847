"""The paper's sample-based optimizers (section III-D) and its baselines, batched over groups.

Each optimizer turns the window costs C (G, K) into an index map (G, K): world k of group g
becomes a copy of world ``index[g, k]``, and a boolean ``explore`` (G, K): which worlds get fresh
parameter noise and a perturbation wrench. All work is torch ops on the device: no host syncs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from inhand_tracker.protocol import METHODS as PROTOCOL_METHODS

__all__ = [
    "HELD_COST",
    "METHODS",
    "OptimizerConfig",
    "Update",
    "duplicates",
    "estimate_pmf",
    "in_place",
    "method_rows",
    "open_loop_worlds",
    "reps_eta",
    "reps_pmf",
    "systematic_resample",
    "update",
    "wrs_pmf",
]

METHODS = PROTOCOL_METHODS  # declared with the protocol, where a session names its method

HELD_COST = 1e8
"""Window costs below this are worlds that still hold their object: a lost one scores 1e9 a frame."""


@dataclass(frozen=True)
class OptimizerConfig:
    method: str = "PBO"
    wrs_lambda: float = 10.0
    """WRS softmax temperature lambda, on costs normalised by their spread in the group."""
    reps_epsilon: float = 0.5
    """REPS KL bound epsilon between the new sample distribution and the uniform one [nats]."""
    pbo_keep: float = 0.35
    """PBO: the fraction K_best / K of worlds kept (the paper does not give it). Measured on the
    paper suite against 0.25 to 0.75: 0.25 is as good, 0.6 and above lose accuracy."""
    pbo_rank_power: float = 1.0
    """PBO: draw the K - K_best copies with weight (K_best - rank) ** p over the kept worlds, rank 0
    the best, still a function of the ordering only; 0 draws them uniformly, as the paper. p = 1
    lowers the paper suite's mean ADD by about 0.4 mm against uniform (paired runs, med noise)."""
    keep_best: bool = True
    """Leave the best world unperturbed, so an update never loses the current estimate."""
    min_spread: float = 0.5
    """Skip the update of a group whose window costs differ by less than this (the default cost
    weighs each term's typical magnitude as 1): before the hand touches the object every world scores
    alike up to noise, and resampling on noise only throws away the spread of initial poses."""
    min_separation: float = 0.0
    """Skip the update of a group whose worlds' window costs differ by less than this many times
    what their own frame-to-frame scatter explains (:func:`.evidence.separation`, an F ratio; 0 never skips).
    The cost is scale-free to the optimizers, so without it a group resamples on whatever differs,
    signal or not."""

    by_evidence: bool = False
    """Make every update only as strong as the evidence for it: the selection (REPS's KL bound, WRS's
    lambda, how many worlds PBO replaces), the parameter and wrench noise, the roughening and the
    estimate's weighting all scale with the information the window's costs hold about which worlds
    are better beyond what noise alone gives (:func:`.evidence.evidence_strength`). Where the worlds are no
    further apart than their own frame-to-frame noise would make them, the group runs open loop and
    its window goes on gathering. Off: every update at full strength, as the paper."""

    open_loop_world: bool = True
    """Under ``by_evidence``, keep world 0 of each group as one open-loop world: seeded at the start
    estimate with the nominal physics and never perturbed, so it follows the robot as dead reckoning
    does; an update at full strength restarts it from the lowest-cost world (state and physics). The
    reported pose leans on it as far as the evidence falls short of a full update (weight 1 - strength
    on the poses), so a group whose sensing tells its worlds nothing reports what one open-loop world
    would, not the mean of worlds spread by its priors, and a lapse of evidence falls back to dead
    reckoning from the last sure estimate."""

    open_loop_ratio: float = 0.0
    """Keep world 0 of each group as its open-loop world (as ``open_loop_world``; without
    ``by_evidence`` never restarted) and report its pose while its window cost summed since the
    group was seeded is within this factor of the lowest-cost world's: where the costs do not tell
    the worlds' poses apart (an object on a palm felt through its weight) the population's best
    explains the robot no better than dead reckoning, and its mean wanders where dead reckoning's
    does not. Once dead reckoning falls behind, the group reports the population. A factor, not
    equality: the lowest of K costs is below one world's by selection alone. 0: off."""

    until_felt: bool = False
    """Until the robot first feels the object after a group is seeded (a fingertip force or touch
    zone over ``cost.contact_threshold``), keep the group's worlds (no update) and report its
    open-loop world (world 0, kept as under ``open_loop_ratio``): a robot whose sensors touch
    nothing knows the object's pose only through its joints, and on a palm those rank the worlds by
    chance. Off: the group updates from its first window."""

    min_pose_evidence: float = 0.0
    """Resample a group's object poses only where they explain its window costs beyond what its
    physics parameters explain (:func:`.evidence.pose_evidence`, an F ratio, over this); elsewhere only the
    parameters are resampled and every world keeps its own state. An object lying on a palm is felt
    through its weight, so the costs rank worlds by mass while the poses are chosen at random, and
    resampling them drifts the estimate away from where the worlds began. 0: always resample both."""

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"optimizer.method: expected one of {METHODS}, got {self.method!r}")
        if not (0.0 < self.pbo_keep <= 1.0):
            raise ValueError(f"optimizer.pbo_keep: expected 0 < fraction <= 1, got {self.pbo_keep}")
        if self.pbo_rank_power < 0:
            raise ValueError(f"optimizer.pbo_rank_power: expected >= 0, got {self.pbo_rank_power}")
        if self.min_pose_evidence < 0:
            raise ValueError(f"optimizer.min_pose_evidence: expected >= 0, got {self.min_pose_evidence}")
        if self.open_loop_ratio != 0 and not 1.0 <= self.open_loop_ratio <= 10.0:
            raise ValueError(f"optimizer.open_loop_ratio: expected 0 (off) or 1 to 10, got {self.open_loop_ratio}")
        if self.min_separation < 0:
            raise ValueError(f"optimizer.min_separation: expected >= 0, got {self.min_separation}")
        if self.reps_epsilon <= 0 or self.wrs_lambda <= 0:
            raise ValueError(
                "optimizer.reps_epsilon and optimizer.wrs_lambda must be positive,"
                f" got {self.reps_epsilon}, {self.wrs_lambda}"
            )


@dataclass
class Update:
    index: torch.Tensor
    """Source world of every world after the update, (G, K) int64."""
    explore: torch.Tensor
    """Worlds to perturb (parameters and wrench), (G, K) bool."""
    held_back: torch.Tensor | None = None
    """Groups whose costs spread but did not separate their worlds beyond noise (``min_separation``,
    or no evidence under ``by_evidence``), (G,) bool: they keep their worlds, and their window
    goes on gathering evidence."""


def wrs_pmf(cost: torch.Tensor, lam: float | torch.Tensor) -> torch.Tensor:
    """Eq. (4): softmax of -lambda (C_i - min C), (G, K); ``lam`` one, or one per group (G, 1).
    Costs are scaled by their spread in the group so that lambda keeps its meaning whatever the
    cost's units."""
    spread = (cost.amax(-1, keepdim=True) - cost.amin(-1, keepdim=True)).clamp_min(1e-12)
    return torch.softmax(-lam * (cost - cost.amin(-1, keepdim=True)) / spread, dim=-1)


def estimate_pmf(cost: torch.Tensor, lam: float | torch.Tensor) -> torch.Tensor:
    """The estimate's weights, (G, K): softmax of -lambda (C_i - min C) / std C over the worlds whose
    cost is below :data:`HELD_COST`; the others weigh nothing (all alike if none is below it).
    The standard deviation, not the range of eq. 4: the range follows the single worst world.
    ``lam``: a number, or one per group (G, 1)."""
    held = cost < HELD_COST
    held = held | ~held.any(-1, keepdim=True)
    n = held.sum(-1, keepdim=True)
    mean = torch.where(held, cost, 0.0).sum(-1, keepdim=True) / n
    std = (torch.where(held, cost - mean, 0.0).square().sum(-1, keepdim=True) / n).sqrt().clamp_min(1e-12)
    low = torch.where(held, cost, torch.inf).amin(-1, keepdim=True)
    return torch.softmax(torch.where(held, -lam * (cost - low) / std, -torch.inf), dim=-1)


def reps_eta(cost: torch.Tensor, epsilon: float | torch.Tensor, iterations: int = 60) -> torch.Tensor:
    """eta* of eq. (5) per group, (G,), by bisection on log eta; ``epsilon`` one bound, or one per
    group (G,).

    With rewards R_i = max C + min C - C_i, the dual's derivative is g'(eta) = epsilon - KL(P_eta || U),
    and the KL falls monotonically as eta grows, so eta* is where the KL meets epsilon. A group
    whose costs cannot reach the bound (all equal, or epsilon >= log K) gets the largest eta tried.
    """
    reward = cost.amax(-1, keepdim=True) + cost.amin(-1, keepdim=True) - cost
    spread = (reward.amax(-1) - reward.amin(-1)).clamp_min(1e-12)
    lo = torch.log(spread * 1e-4)
    hi = torch.log(spread * 1e4)
    log_k = math.log(cost.shape[-1])
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        logp = torch.log_softmax(reward / mid.exp()[:, None], dim=-1)
        kl = (logp.exp() * logp).sum(-1) + log_k
        too_sharp = kl > epsilon  # KL above the bound: eta must grow
        lo = torch.where(too_sharp, mid, lo)
        hi = torch.where(too_sharp, hi, mid)
    return (0.5 * (lo + hi)).exp()


def reps_pmf(cost: torch.Tensor, epsilon: float | torch.Tensor) -> torch.Tensor:
    """Eq. (6): softmax of R_i / eta*, (G, K); ``epsilon`` one bound, or one per group (G,)."""
    reward = cost.amax(-1, keepdim=True) + cost.amin(-1, keepdim=True) - cost
    return torch.softmax(reward / reps_eta(cost, epsilon)[:, None], dim=-1)


def systematic_resample(pmf: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """K draws per group from ``pmf`` (G, K) by systematic resampling: one uniform offset and K
    evenly spaced points, so each world is copied floor or ceil of K p_i times. Unlike independent
    draws it keeps every world of a flat PMF."""
    g, k = pmf.shape
    offset = torch.rand((g, 1), generator=gen, device=pmf.device)
    points = (torch.arange(k, device=pmf.device) + offset) / k
    cdf = torch.cumsum(pmf, dim=-1)
    cdf = cdf / cdf[:, -1:]
    return torch.searchsorted(cdf, points).clamp_(max=k - 1)


def in_place(index: torch.Tensor) -> torch.Tensor:
    """The resample ``index`` (G, K) with every surviving world in its own slot: each source keeps
    its slot, and its second and later copies fill the slots of the worlds it dropped, in order.
    The same worlds and copies, so a world an update keeps is left as it was, state and physics
    together. Scatters and cumulative sums, without a sync."""
    g, k = index.shape
    slots = torch.arange(k, device=index.device).expand(g, k)
    dropped = torch.zeros(g, k, dtype=torch.bool, device=index.device).scatter(1, index, True).logical_not()
    extra = duplicates(index)  # as many per group as the worlds dropped
    pad = torch.full((g, k + 1), k, dtype=index.dtype, device=index.device)
    # The r-th extra copy's source and the r-th dropped slot; everything else to the pad column k.
    sources = pad.scatter(1, torch.where(extra, extra.cumsum(-1) - 1, k), index)
    targets = pad.scatter(1, torch.where(dropped, dropped.cumsum(-1) - 1, k), slots)
    out = torch.cat([slots, pad[:, :1]], -1).scatter(1, targets[:, :k], sources[:, :k])
    return out[:, :k]


def duplicates(index: torch.Tensor) -> torch.Tensor:
    """Which worlds of a resample ``index`` (G, K) are a second or later copy of their source,
    (G, K) bool. On the device, without a sync: each source's first slot is a scatter-min."""
    g, k = index.shape
    slots = torch.arange(k, device=index.device).expand(g, k)
    first = torch.full((g, k), k, dtype=index.dtype, device=index.device).scatter_reduce(1, index, slots, "amin")
    return first.gather(1, index) != slots


def open_loop_worlds(config: OptimizerConfig, worlds: int, device: torch.device) -> torch.Tensor:
    """Which world of each group is kept as its open-loop world (``config.open_loop_world``), (1, K)
    bool: world 0 under ``by_evidence``, ``open_loop_ratio`` or ``until_felt`` where a group has more
    than one; none otherwise."""
    reports_it = config.open_loop_ratio > 0 or config.until_felt
    anchored = ((config.by_evidence and config.open_loop_world) or reports_it) and worlds > 1
    return (torch.arange(worlds, device=device) == 0)[None] & anchored


def update(
    cost: torch.Tensor,
    config: OptimizerConfig,
    gen: torch.Generator,
    methods: tuple[str, ...] | None = None,
    rows: dict[str, torch.Tensor] | None = None,
    separated: torch.Tensor | None = None,
    strength: torch.Tensor | None = None,
    hold: torch.Tensor | None = None,
) -> Update:
    """One optimizer update of every group from the window costs ``cost`` (G, K).

    ``separated`` (G,) is each group's :func:`.evidence.separation`; a group below ``config.min_separation``
    keeps its worlds as they are, like one whose costs spread less than ``config.min_spread``,
    but for those that lost their object, and is named in :attr:`Update.held_back`. ``strength``
    (G, 1) in [0, 1] (:func:`.evidence.evidence_strength`) weakens each group's selection; at 0 the group is
    held back as well. None: every group at full strength. Under ``config.until_felt``, ``hold`` (G,)
    bool holds groups back whatever their costs.

    ``methods`` (G,) gives each group its own method (a benchmark suite runs all methods as groups
    of one population); default ``config.method`` for all. The loop is over methods, not worlds.
    ``rows`` maps each method present to its groups, a (G,) bool tensor on the device; a caller
    that captures the update passes it, since building it from ``methods`` copies from the host."""
    informative = cost.amax(-1) - cost.amin(-1) > config.min_spread
    held_back = torch.zeros_like(informative)
    if separated is not None and config.min_separation > 0:
        held_back = informative & (separated <= config.min_separation)
    if strength is not None:
        held_back = held_back | (informative & (strength[:, 0] <= 0))
    if hold is not None and config.until_felt:
        held_back = held_back | (informative & hold)
    informative = informative & ~held_back
    if methods is None or len(set(methods)) == 1:
        method = config.method if methods is None else methods[0]
        part = _update(cost, method, config, gen, informative, strength)
        return Update(index=part.index, explore=part.explore, held_back=held_back)
    if rows is None:
        rows = method_rows(methods, cost.device)
    index = explore = None
    for method in sorted(set(methods)):
        part = _update(cost, method, config, gen, informative, strength)
        mine = rows[method][:, None]
        index = part.index if index is None else torch.where(mine, part.index, index)
        explore = part.explore if explore is None else torch.where(mine, part.explore, explore)
    return Update(index=index, explore=explore, held_back=held_back)


def method_rows(methods: tuple[str, ...], device: torch.device) -> dict[str, torch.Tensor]:
    """For every method, which groups use it: (G,) bool on ``device``."""
    return {m: torch.tensor([x == m for x in methods], device=device) for m in METHODS}


def _update(
    cost: torch.Tensor,
    method: str,
    config: OptimizerConfig,
    gen: torch.Generator,
    informative: torch.Tensor,
    strength: torch.Tensor | None = None,
) -> Update:
    """One method's update of every group; groups not ``informative`` (G,) keep their worlds, and
    ``strength`` (G, 1) in [0, 1] weakens each group's selection (None: full), whose kept worlds
    then stay in their own slots (:func:`in_place`): a world replaced only in part, taking another's
    physics and keeping its pose, must be told from one the update left alone."""
    g, k = cost.shape
    dev = cost.device
    identity = torch.arange(k, device=dev).expand(g, k)
    if method in ("OLP", "EYE"):
        return Update(index=identity.clone(), explore=torch.zeros(g, k, dtype=torch.bool, device=dev))
    if method == "PBO":
        index = _pbo_index(cost, config, gen, strength)
    else:
        # Eq. 4 and 6 scale the costs by their spread: a lost world's 1e9 would make every world
        # that still holds the object weigh alike. They are scored among themselves; the lost draw none.
        held = cost < HELD_COST
        held = held | ~held.any(-1, keepdim=True)
        among = torch.where(held, cost, torch.where(held, cost, -torch.inf).amax(-1, keepdim=True))
        full = torch.ones(g, 1, device=dev) if strength is None else strength
        if method == "WRS":
            pmf = wrs_pmf(among, config.wrs_lambda * full)
        else:  # a KL bound that shrinks to 0 with the evidence: the uniform draw, every world kept once
            pmf = reps_pmf(among, config.reps_epsilon * full[:, 0])
        index = systematic_resample(torch.where(held, pmf, 0.0), gen)
    best = cost.argmin(-1, keepdim=True)
    if strength is None:  # the paper's: the best world to slot 0, where keep_best leaves it unperturbed
        index = torch.cat([best, index[:, 1:]], -1) if method != "PBO" else index
        explore = identity != 0
    else:  # a world the update keeps stays in its own slot, its state and physics together: the best too
        index = in_place(index).scatter(1, best, best)
        explore = identity != best
    explore = explore if config.keep_best else torch.ones(g, k, dtype=torch.bool, device=dev)
    # A group held back still replaces the worlds that lost their object, from those that did not.
    lost = cost >= HELD_COST
    go = informative[:, None] | (lost & ~lost.all(-1, keepdim=True))
    return Update(index=torch.where(go, index, identity), explore=explore & go)


def _pbo_index(cost: torch.Tensor, config: OptimizerConfig, gen: torch.Generator, strength: torch.Tensor | None):
    """PBO's sources (G, K): the K_best lowest-cost worlds stay, the others are replaced by copies
    drawn over them with weight (K_best - rank) ** p. ``strength`` (G, 1) keeps more worlds where
    the evidence is weak: K - strength (K - K_best), all of them at 0."""
    g, k = cost.shape
    dev = cost.device
    keep = max(1, round(config.pbo_keep * k))
    order = torch.argsort(cost, dim=-1)
    if strength is None:
        kept = torch.full((g, 1), keep, device=dev, dtype=cost.dtype)
    else:
        kept = torch.round(k - strength * (k - keep)).clamp(keep, k)
    rank = torch.arange(k, device=dev, dtype=cost.dtype).expand(g, k)
    # p = 0 makes every weight 1: the paper's uniform draw is the same path.
    weight = torch.where(rank < kept, (kept - rank).clamp_min(0) ** config.pbo_rank_power, 0.0)
    cdf = torch.cumsum(weight, -1)
    cdf = cdf / cdf[:, -1:]
    # Inverse CDF rather than torch.multinomial: the same capture-safe ops as systematic_resample.
    u = torch.rand((g, k), generator=gen, device=dev, dtype=cost.dtype)
    pick = torch.searchsorted(cdf, u.contiguous()).clamp_(max=k - 1)
    return torch.where(rank < kept, order, torch.gather(order, 1, pick))
