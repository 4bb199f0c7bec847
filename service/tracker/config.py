"""The tracker's settings: one frozen dataclass, every default in one place."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from .cost import CostConfig
from .optimizers import OptimizerConfig

__all__ = ["TrackerConfig", "setting_types"]


@dataclass(frozen=True)
class TrackerConfig:
    update_every: int = 15
    """T: frames between optimizer updates."""
    sigma_t: float = 0.005
    """Initial pose noise, translation standard deviation [m] (Sigma_p)."""
    sigma_r: float = 0.1
    """Initial pose noise, rotation standard deviation [rad] (Sigma_p)."""
    mass_sigma0: float = 0.25
    """Initial mass spread, as a fraction of the object's mass range."""
    friction_sigma0: float = 0.25
    """Initial friction spread, as a fraction of the friction range."""
    mass_sigma: float = 0.05
    """Exploration: mass noise per update, fraction of the range (Sigma_theta)."""
    friction_sigma: float = 0.05
    """Exploration: friction noise per update, fraction of the range (Sigma_theta)."""
    softness_sigma0: float = 0.5
    """Spread of the object's contact time constant (MuJoCo's solref: how soft its contacts are)
    drawn when a group's contact exploration opens, standard deviation of its logarithm, within a
    factor of 4 of the model's. 0 (with impratio_sigma0 and both per-update noises): every world
    keeps the model's contacts. Exploring them pays only where the model's contacts are wrong and
    the worlds are many: drawn from the start at 1024 worlds it cut the error against MuJoCo C's
    truth from 8.7 to 5.9 mm but added 1.7 mm where the truth is the model itself, and at K=40 it
    added 5 mm there (docs/benchmarks.md); hence the gate (contact_gate_cost)."""
    impratio_sigma0: float = 0.5
    """Spread of the contacts' impratio (how stiffly they resist sliding) drawn when the
    exploration opens, standard deviation of its logarithm, within a factor of 4 of the model's."""
    softness_sigma: float = 0.1
    """Exploration once open: noise of the time constant's logarithm per update."""
    impratio_sigma: float = 0.1
    """Exploration once open: noise of the impratio's logarithm per update."""
    contact_gate_cost: float = 4.0
    """A group's worlds keep the model's contacts until its lowest window cost (the mean cost per
    frame of its best world, which no world explains) has stayed above this for
    ``contact_gate_updates`` updates in a row; then they draw their contacts with the spreads
    above and explore them at every update, for the rest of the session. The lowest cost
    separates the model being right from it being wrong: medians of 0.2-0.4 (1.1 on the Shadow
    Hand) where the truth is the tracker's own physics, 12-38 against a reality gap or another
    engine. Paired at K=1024 on an H100 it opened on every cross-engine and reality-gap track and
    cut the error against MuJoCo C from 10.2 to 7.0 mm (PBO) and 8.5 to 6.8 (REPS); on the paper
    suite it opened on the toy banana's gaiting only (2 of 12 tracks). 0: no gate, the contacts
    are drawn when the worlds are seeded."""
    contact_gate_updates: int = 4
    """Updates in a row above ``contact_gate_cost`` that open the contact exploration: one window
    of a hard contact event does not say the model is wrong."""
    contact_worlds: int = 1024
    """Contact exploration only in groups of at least this many worlds. At K=40 the two extra
    dimensions thin the population: drawn from the start they cost 4.6-5.5 mm where the truth is
    the model and bought nothing against MuJoCo C's truth, and gated they opened on 44 % of the
    paper suite's tracks, whose error rose from 4.3 to 6.9 mm (explored tracks against the rest)."""
    wrench_force: float = 0.05
    """Exploration: perturbation force standard deviation [N] (Sigma_v)."""
    wrench_torque: float = 0.001
    """Exploration: perturbation torque standard deviation [N m] (Sigma_v)."""
    jitter_t: float = 0.0005
    """Exploration beyond the paper: the object of every second or later copy of a world is
    displaced at an update, translation standard deviation [m]. Copies are exact, and a held
    object's pose along directions the sensors cannot see (a shift or turn about the squeeze) is
    kept by friction, so without it K=40 collapsed onto one wrong grasp outcome within a few
    updates and never left it (roughening, as in particle filters)."""
    jitter_r: float = 0.01
    """The same displacement's rotation standard deviation [rad], about the object's origin."""
    jitter_bandwidth: float = 1.0
    """Where a group's worlds disagree more than that, the displacement grows with their spread
    (RMS per axis of position and of rotation), up to sigma_t and sigma_r: a kernel of the
    population's own width, as regularised particle filters draw it. Its width is this multiple
    of Silverman's rule of thumb for K poses (0.645 of the spread at K=40, 0.41 at 4096). With
    the fixed displacement alone, a K=40 population still collapsed and drifted as one: in
    about one box track in twenty of the paper suite every world ended 40 to 80 mm off, the
    nearest no closer than the estimate. 0: jitter_t and jitter_r only."""
    jitter_shrink_worlds: int = 256
    """In groups of at least this many worlds, every displaced copy first moves 1 - sqrt(1 - h^2)
    of the way to its group's mean pose, h being the displacement's width as a share of the
    spread (Liu and West's shrinkage): the roughening then keeps the group's spread instead of
    adding h^2 of it at every update. On an H100 at med noise it cut the paper suite's ADD by
    0.4 mm at K=256 and 0.7 mm at K=1024, and the reality gap's by 0.5 mm at K=1024, with the
    cross-engine suite unchanged; at K=40, where 14 distinct worlds estimate the spread, the
    extra spread still guards against collapse (0.2 to 0.7 mm worse with the shrinkage). 0: never."""
    mean_estimate: bool = True
    """Report the cost-weighted mean of the worlds' object poses as the estimate; False: the
    lowest-cost world's (the paper's). Costs a few millimetres apart barely
    separate worlds (before the hand touches the object they do not at all), so one world picked
    among them carries their spread as error, which the mean averages out: the mean was the
    better estimate for REPS and PBO on the paper, reality-gap and cross-engine suites alike."""
    estimate_lambda: float = 2.0
    """Sharpness of the cost weights behind the mean pose and covariance: softmax of
    -lambda (C - min C) / std C over the worlds that still hold the object (:func:`.optimizers.estimate_pmf`).
    Scaled by the costs' range instead, as WRS's are, the weights followed the worst world: one
    world that dropped its object made them all alike. With lambda 2 the mean was 0.03-0.4 mm
    closer to the truth than with the range at 5 on the paper, reality-gap and cross-engine suites
    at K = 40, 256 and 1024 (H100, med noise)."""
    lost_fraction: float = 0.9
    """Diverged when more than this fraction of a group's worlds lost the object."""
    contact_loss_frames: int = 5
    """Diverged when the best world disagrees with the real robot about contact on at least half
    of the sensors for this many frames in a row (the real hand holds the object, no world does).
    A cost-level rule fired falsely whenever contact began: the normalised cost is not stationary
    across approach, grasp and transport."""
    uncertain_spread: float = 0.015
    """Uncertain when the object's surface points spread more than this [m] (RMS) across the
    weighted worlds: position and rotation together, the error in ADD that the worlds' spread
    allows. Position alone missed the turned objects: at high initial noise a brick or a can whose
    worlds agree on where it is but not on how it is turned was reported tracking while 20 to 90 mm
    off."""
    covariance_floor_t: float = 0.002
    """Standard deviation [m] added to the reported position covariance at the reference cost
    (``covariance_cost_ref``): what the physics cannot resolve because the model is not the robot.
    Its variance grows with the lowest window cost, the part of what the robot sensed that no world
    explains, up to 16 times (4x this deviation). A constant floor could not be honest on both
    sides: where the model is the truth's (the paper suite) the best world's cost is 0.2-0.4 and
    the worlds' own spread covers the truth on 95 % of frames at K=1024 (100 % with a constant
    floor); across a reality gap or another engine the cost is 12-37 and the spread alone covers
    9-39 %. The estimate and the track state ignore it."""
    covariance_floor_r: float = 0.05
    """The same for the rotation vector [rad]."""
    covariance_cost_ref: float = 18.0
    """The lowest window cost at which the floor is ``covariance_floor_t`` and ``_r``: about what a
    well-tracking group scores against a robot with sensor noise (15-16 on the reality-gap suite;
    each of the cost's terms is weighted to about 1 at its typical magnitude)."""
    covariance_resolution: float = 5.0
    """Also added: the variance the group was last seeded with (its initial pose noise) times this
    over K. The worlds sample the start region, and the fewer they are, the coarser they resolve it,
    which their spread after resampling does not show: on the paper suite at K=40 the spread alone
    covers 48 % of frames (a 2 mm error against a 1-2 mm spread)."""
    mode_angle: float = 0.5
    """Worlds within this angle [rad] and ``mode_distance`` of a mode's seed belong to that mode."""
    mode_distance: float = 0.02
    """[m] (see ``mode_angle``)."""
    ambiguous_weight: float = 0.25
    """Ambiguous when the second pose mode (the heaviest worlds away from the lowest-cost world's
    mode) carries at least this share of the cost weights: contact cannot tell the two apart
    (a turned brick, a can about its axis)."""
    surprise_ratio: float = 8.0
    """Uncertain while the best world's window cost is above this multiple of its recent level (a
    running mean over ``surprise_frames``) and above ``surprise_cost``: the robot feels something
    that no world explains, e.g. the object slipping or set down faster than the worlds move it;
    0: off. The worlds' spread and modes lag such an event: at high initial noise on the paper
    suite the banana, set down, dropped 12 mm in 0.2 s and the estimate was 28 mm off for 0.1 s
    while the status said tracking. Replayed on the saved frames of 12 runs (the paper,
    reality-gap and cross-engine suites, both hands, K=40 and 1024) the rule flagged that and 6 of
    19 unflagged errors past 20 mm on the paper suite at K=40, and raised the share of frames under
    10 mm reported untrusted by at most 0.005 on any suite. A surprise does not hold back the
    re-seeding anchor, which follows the contacts' agreement."""
    surprise_cost: float = 8.0
    """The lowest window cost below which no rise counts as a surprise (see ``surprise_ratio``):
    a well-tracking group scores 0.2-0.4 against its own physics and 12-38 across a reality gap or
    another engine."""
    surprise_frames: int = 30
    """Frames over which the recent level of the best world's window cost is averaged
    (exponentially; 1 s at 30 Hz)."""
    reseed_scale: float = 3.0
    """Re-seeding noise, as a multiple of sigma_t and sigma_r."""
    drop_sigma_t: float = 0.03
    """Re-seeding after a drop: horizontal spread of the hypotheses on the table [m] (a falling
    object bounces and rolls; the rotation spread is the re-seeding one)."""
    recover_frames: int = 20
    """Frames a re-seeded group reports RECOVERING before it is trusted again."""
    observation_weight: float = 1.0
    """A pose observation's weight in the window cost: a world at the observation's 95 % bound
    (Mahalanobis distance squared 12.6, 6 dof) scores as much worse as the spread of the group's
    contact costs. Scaled by that spread, the cost's units do not matter."""
    observation_gate: float = 22.5
    """No world within this Mahalanobis distance squared of a confident observation (6 dof, 0.999)
    re-seeds the group around the observation."""
    inject_share: float = 0.1
    """Share of a group's worlds, the least likely, drawn afresh around a confident observation
    that the worlds agree with less than its noise allows (beyond ``inject_gate``, short of
    ``observation_gate``, where the whole group is re-seeded); 0: none. With the object dropped
    mid-carry and a camera at 1 Hz, every track's estimate came back within 10 mm
    (docs/benchmarks.md)."""
    inject_gate: float = 12.59
    """Mahalanobis distance squared of the nearest world beyond which a confident observation
    draws ``inject_share`` of the worlds around itself (6 dof, 0.95)."""
    observation_confident: float = 0.02
    """An observation is confident when its largest position standard deviation is below this [m]."""
    seed: int = 0
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    cost: CostConfig = field(default_factory=CostConfig)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"tracker {f.name}: expected a finite number, got {value}")
        if not 0.0 <= self.inject_share <= 1.0:
            raise ValueError(f"tracker inject_share: expected 0 to 1, got {self.inject_share}")
        if self.jitter_shrink_worlds < 0:
            got = self.jitter_shrink_worlds
            raise ValueError(f"tracker jitter_shrink_worlds: expected >= 0 worlds (0: never), got {got}")
        if not (self.covariance_cost_ref > 0 and self.covariance_resolution >= 0):
            raise ValueError(
                f"tracker covariance_cost_ref: expected > 0 (got {self.covariance_cost_ref}) and"
                f" covariance_resolution >= 0 (got {self.covariance_resolution})"
            )
        if self.contact_worlds < 1:
            raise ValueError(f"tracker contact_worlds: expected >= 1 world, got {self.contact_worlds}")
        if self.contact_gate_updates < 1:
            raise ValueError(f"tracker contact_gate_updates: expected >= 1 update, got {self.contact_gate_updates}")
        if self.surprise_frames < 1:
            raise ValueError(f"tracker surprise_frames: expected >= 1 frame, got {self.surprise_frames}")
        if self.update_every < 1:
            raise ValueError(f"tracker update_every: expected >= 1 frame, got {self.update_every}")
        noise = ("sigma_t", "sigma_r", "wrench_force", "wrench_torque", "jitter_t", "jitter_r", "jitter_bandwidth")
        contacts = ("softness_sigma0", "impratio_sigma0", "softness_sigma", "impratio_sigma", "contact_gate_cost")
        others = ("mass_sigma", "friction_sigma", "inject_gate", "surprise_ratio", "surprise_cost")
        for name in (*noise, *contacts, *others):
            if getattr(self, name) < 0:
                raise ValueError(f"tracker {name}: expected >= 0, got {getattr(self, name)}")


def setting_types(config: type, kinds: tuple[type, ...] = (int, float)) -> dict[str, type]:
    """The fields of the settings dataclass ``config`` whose defaults are of ``kinds``, with their
    types: what a session's overrides and ``bench accuracy --set`` may change."""
    out = {f.name: type(f.default) for f in fields(config) if type(f.default) in kinds}
    # An optional number (None: the library's own default) is set as the number.
    out |= {f.name: k for f in fields(config) for k in kinds if f.default is None and f.type == f"{k.__name__} | None"}
    return out
