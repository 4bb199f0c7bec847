"""The tracker's settings, nested by concern; every default in one place. Why each default is what
it is, with the measurements behind it, is in docs/tracker-settings.md.

A setting is named by its path in this nesting (``exploration.jitter_bandwidth``) wherever a user
changes it: a session's overrides, ``bench accuracy --set``, a run's results (:mod:`.settings`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from .cost import CostConfig
from .optimizers import OptimizerConfig

__all__ = [
    "TRACKER_GROUPS",
    "ContactExploration",
    "EstimateConfig",
    "Exploration",
    "ObservationConfig",
    "RecoveryConfig",
    "Seeding",
    "ServoExploration",
    "TrackerConfig",
]


_INF = math.inf
_GROUP_OF = {
    "Seeding": "seeding",
    "Exploration": "exploration",
    "ContactExploration": "contacts",
    "ServoExploration": "servos",
    "EstimateConfig": "estimate",
    "RecoveryConfig": "recovery",
    "ObservationConfig": "observations",
}
"""Each settings group's name in TrackerConfig: the first part of its settings' dotted names."""


def _check(config, ranges: dict[str, tuple[float, float, str]]) -> None:
    """Refuse non-finite numbers, and settings outside their range (low, high, unit), naming the
    setting by its dotted name (:mod:`.settings`), the range and the value. The ranges are what the
    settings can mean: fractions of a range at most 1, poses and spreads within a hand's reach."""
    group = _GROUP_OF.get(type(config).__name__, "")
    dotted = lambda name: f"{group}.{name}" if group else name  # noqa: E731
    for f in fields(config):
        value = getattr(config, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{dotted(f.name)}: expected a finite number, got {value}")
    for name, (low, high, unit) in ranges.items():
        value = getattr(config, name)
        if not low <= value <= high:
            wanted = f">= {low:g}" if high == _INF else f"{low:g} to {high:g}"
            raise ValueError(f"{dotted(name)}: expected {wanted}{unit}, got {value}")


@dataclass(frozen=True)
class Seeding:
    """Where a group's worlds start: drawn around the initial pose estimate (Sigma_p) and the
    object's nominal physics."""

    sigma_t: float = 0.005
    """Initial pose noise, translation standard deviation [m]."""
    sigma_r: float = 0.1
    """Initial pose noise, rotation standard deviation [rad]."""
    mass_sigma0: float = 0.25
    """Initial mass spread, as a fraction of the object's mass range."""
    friction_sigma0: float = 0.25
    """Initial friction spread, as a fraction of the friction range."""

    def __post_init__(self) -> None:
        fraction = (0.0, 1.0, "")
        ranges = {"sigma_t": (0.0, 0.1, " m"), "sigma_r": (0.0, 3.2, " rad")}
        _check(self, ranges | {"mass_sigma0": fraction, "friction_sigma0": fraction})


@dataclass(frozen=True)
class Exploration:
    """What every update perturbs in the resampled worlds (Sigma_theta, Sigma_v, and the
    roughening of their object poses, beyond the paper)."""

    mass_sigma: float = 0.05
    """Mass noise per update, fraction of the range."""
    friction_sigma: float = 0.05
    """Friction noise per update, fraction of the range."""
    wrench_force: float = 0.05
    """Perturbation force standard deviation [N]."""
    wrench_torque: float = 0.001
    """Perturbation torque standard deviation [N m]."""
    jitter_t: float = 0.0005
    """Every second or later copy of a world has its object displaced by this much, translation
    standard deviation [m]: copies are exact, and friction keeps a held object's pose along what
    the sensors cannot see, so without it a small population collapses onto one grasp outcome."""
    jitter_r: float = 0.01
    """The same displacement's rotation standard deviation [rad], about the object's origin."""
    jitter_bandwidth: float = 1.0
    """Where the worlds disagree more than the fixed displacement, it grows with their spread (a
    kernel of the population's own width, as regularised particle filters draw it), up to sigma_t
    and sigma_r; its width is this multiple of Silverman's rule for K poses. 0: jitter_t and
    jitter_r only."""
    jitter_shrink_worlds: int = 1
    """In groups of at least this many worlds, every displaced copy first moves 1 - sqrt(1 - h^2)
    of the way to the group's mean (Liu and West's shrinkage), so the roughening keeps the spread
    instead of adding to it at every update. Without it, where the sensing cannot tell the worlds
    apart (an object resting on a palm), each update widens a small group and its mean wanders
    with it. 0: never."""
    keep_mean: bool = False
    """After every update the displaced copies move together so that the group's mean pose is the
    estimate's mean over all worlds just before it: resampling redistributes the worlds without
    moving the belief's mean, which its random draws otherwise walk where the costs rank the worlds
    by their physics rather than their poses (an object resting on a palm). Where the costs do rank
    the poses it undoes what the update learned, and where the worlds split into modes it moves the
    copies between them: off."""
    undo_chance_shift: bool = False
    """After every update, along each direction of the object's pose (translation along the world's
    axes, rotation about the mean's), the displaced copies move together to undo the resampling's
    move of the worlds' mean as far as a selection at random with the same copy counts would have
    made it (:func:`.sampling.chance_shift`): kept from twice that chance's standard deviation,
    undone within once it. The belief's mean then moves only as far as the costs tell, not by the
    draw: an object lying on a palm and felt through its weight keeps its place along the palm and
    its turn about the vertical through updates that rank the worlds by their mass. ``keep_mean``
    on keeps every direction whatever the update."""

    def __post_init__(self) -> None:
        _check(
            self,
            {
                "mass_sigma": (0.0, 1.0, ""),
                "friction_sigma": (0.0, 1.0, ""),
                "wrench_force": (0.0, 10.0, " N"),
                "wrench_torque": (0.0, 1.0, " N m"),
                "jitter_t": (0.0, 0.1, " m"),
                "jitter_r": (0.0, 3.2, " rad"),
                "jitter_bandwidth": (0.0, 10.0, ""),
                "jitter_shrink_worlds": (0, _INF, " worlds (0: never)"),
            },
        )


@dataclass(frozen=True)
class ContactExploration:
    """Exploring the contacts' softness and impratio, where the cost says the model's are wrong.
    It pays only with many worlds and a wrong model, and costs accuracy where the model is right,
    hence the gate."""

    softness_sigma0: float = 0.5
    """Spread of the object's contact time constant (MuJoCo's solref) drawn when the exploration
    opens, standard deviation of its logarithm, within a factor of 4 of the model's."""
    impratio_sigma0: float = 0.5
    """Spread of the contacts' impratio (how stiffly they resist sliding) drawn when it opens,
    standard deviation of its logarithm, within a factor of 4 of the model's."""
    softness_sigma: float = 0.1
    """Once open: noise of the time constant's logarithm per update."""
    impratio_sigma: float = 0.1
    """Once open: noise of the impratio's logarithm per update."""
    contact_gate_cost: float = 4.0
    """The exploration opens once the group's lowest window cost (what no world explains) stayed
    above this for ``contact_gate_updates`` updates in a row, for the rest of the session: the
    lowest cost tells a right model (well below 1-2) from a wrong one (tens). 0: no gate, the
    contacts are drawn when the worlds are seeded."""
    contact_gate_updates: int = 4
    """Updates in a row above the gate that open it: one hard contact event does not say the model is wrong."""
    contact_worlds: int = 1024
    """Contact exploration only in groups of at least this many worlds: two more dimensions thin
    a small population more than they help it."""

    def __post_init__(self) -> None:
        spread = (0.0, 5.0, "")
        _check(
            self,
            dict.fromkeys(("softness_sigma0", "impratio_sigma0", "softness_sigma", "impratio_sigma"), spread)
            | {
                "contact_gate_cost": (0.0, _INF, ""),
                "contact_gate_updates": (1, _INF, " update"),
                "contact_worlds": (1, _INF, " world"),
            },
        )

    @property
    def any(self) -> bool:
        """Whether any contact parameter is ever drawn."""
        return max(self.softness_sigma0, self.impratio_sigma0, self.softness_sigma, self.impratio_sigma) > 0


@dataclass(frozen=True)
class ServoExploration:
    """Exploring the strength of each finger's servos, where the model check says the hand does
    not follow the robot's joints: the worlds scale a chain's servo gain, damping and effort limit
    and its joints' own damping by one factor (a servo twice as strong is all four), drawn around
    the config's, as a calibration's search scales them together. Off by default: a calibrated
    robot needs none of it."""

    servo_sigma0: float = 0.0
    """Spread of a chain's strength drawn when its exploration opens, standard deviation of its
    logarithm, within a factor of 4 of the config's; 0: off."""
    servo_sigma: float = 0.1
    """Once open: noise of the strength's logarithm per update."""
    servo_gate: float = 0.01
    """A chain's exploration opens once one of its joints ran further than this [rad or m] (RMS,
    the model check's nearest world) from the measured one for ``servo_gate_updates`` updates in a
    row, for the rest of the session: twice the joint noise of a real hand's encoders, a third of
    what the service's model check reports."""
    servo_gate_updates: int = 4
    """Updates in a row past the gate that open it: a finger blocked by the object for a moment
    does not say its servo is wrong."""
    servo_worlds: int = 2
    """Servo exploration only in groups of at least this many worlds."""

    def __post_init__(self) -> None:
        _check(
            self,
            {
                "servo_sigma0": (0.0, 5.0, ""),
                "servo_sigma": (0.0, 5.0, ""),
                "servo_gate": (0.0, _INF, " rad or m"),
                "servo_gate_updates": (1, _INF, " update"),
                "servo_worlds": (2, _INF, " world"),
            },
        )


@dataclass(frozen=True)
class EstimateConfig:
    """What an estimate reports: the pose, its covariance and its modes."""

    mean_estimate: bool = True
    """Report the cost-weighted mean of the worlds' object poses; False: the lowest-cost world's
    (the paper's). Costs a few millimetres apart barely separate worlds, so one world picked
    among them carries their spread as error, which the mean averages out."""
    mean_over_mode: bool = True
    """Report the mean over the worlds of the lowest-cost world's mode (within ``mode_angle`` and
    ``mode_distance`` of it) rather than over all: where the worlds split, as when the object left
    the hand in some and not in others, the mean of all lies between the modes, where none is.
    Where the worlds agree the mode holds all of them. ``mean_pose``, the covariance and the
    re-seeding anchor stay those of all the worlds."""
    estimate_lambda: float = 2.0
    """Sharpness of the weights behind the mean pose and covariance: softmax of
    -lambda (C - min C) / std C over the worlds that still hold the object. Scaled by the standard
    deviation, not the range: one world that dropped its object must not flatten the others' weights."""
    covariance_floor_t: float = 0.002
    """Standard deviation [m] added to the reported position covariance at the reference cost:
    what the physics cannot resolve because the model is not the robot. Its variance grows with
    the lowest window cost, up to 16 times; the estimate and the track state ignore it."""
    covariance_floor_r: float = 0.05
    """The same for the rotation vector [rad]."""
    covariance_cost_ref: float = 18.0
    """The lowest window cost at which the floor is ``covariance_floor_t`` and ``_r``: about what a
    well-tracking group scores against a robot with sensor noise."""
    covariance_resolution: float = 5.0
    """Also added: the variance the group was last seeded with times this over K. K worlds resolve
    the start region only so finely, and their spread after resampling does not show it."""
    mode_angle: float = 0.5
    """Worlds within this angle [rad] and ``mode_distance`` of a mode's seed belong to that mode."""
    mode_distance: float = 0.02
    """[m] (see ``mode_angle``)."""

    def __post_init__(self) -> None:
        _check(
            self,
            {
                "estimate_lambda": (0.0, 100.0, ""),
                "covariance_floor_t": (0.0, 1.0, " m"),
                "covariance_floor_r": (0.0, 3.2, " rad"),
                "covariance_cost_ref": (1e-9, _INF, ""),
                "covariance_resolution": (0.0, _INF, ""),
                "mode_angle": (0.0, 3.2, " rad"),
                "mode_distance": (0.0, 1.0, " m"),
            },
        )


@dataclass(frozen=True)
class RecoveryConfig:
    """The track state (tracking, uncertain, ambiguous, diverged, recovering) and the re-seeding
    of a group that diverged."""

    lost_fraction: float = 0.9
    """Diverged when more than this fraction of a group's worlds lost the object."""
    contact_loss_frames: int = 5
    """Diverged when the best world disagrees with the real robot about contact on at least half
    of the sensors for this many frames in a row (the real hand holds the object, no world does)."""
    uncertain_spread: float = 0.015
    """Uncertain when the object's surface points spread more than this [m] (RMS) across the
    weighted worlds: position and rotation together, as ADD sees them."""
    ambiguous_weight: float = 0.25
    """Ambiguous when the second pose mode carries at least this share of the weights: contact
    cannot tell the two apart (a turned brick, a can about its axis)."""
    surprise_ratio: float = 8.0
    """Uncertain while the best world's window cost is above this multiple of its recent level and
    above ``surprise_cost``: the robot feels something no world explains (a slip, a set-down faster
    than the worlds move), which the worlds' spread shows only later. 0: off."""
    surprise_cost: float = 8.0
    """The lowest window cost below which no rise counts as a surprise."""
    surprise_frames: int = 30
    """Frames over which the recent level of the best world's window cost is averaged (exponentially)."""
    reseed_scale: float = 3.0
    """Re-seeding noise, as a multiple of sigma_t and sigma_r."""
    drop_sigma_t: float = 0.03
    """Re-seeding after a drop: horizontal spread of the hypotheses on the table [m] (a falling
    object bounces and rolls)."""
    recover_frames: int = 20
    """Frames a re-seeded group reports RECOVERING before it is trusted again."""

    def __post_init__(self) -> None:
        _check(
            self,
            {
                "lost_fraction": (0.0, 1.0, ""),
                "contact_loss_frames": (1, _INF, " frame"),
                "uncertain_spread": (0.0, 1.0, " m"),
                "ambiguous_weight": (0.0, 1.0, ""),
                "surprise_ratio": (0.0, _INF, ""),
                "surprise_cost": (0.0, _INF, ""),
                "surprise_frames": (1, _INF, " frame"),
                "reseed_scale": (0.0, 100.0, ""),
                "drop_sigma_t": (0.0, 1.0, " m"),
                "recover_frames": (0, _INF, " frames"),
            },
        )


@dataclass(frozen=True)
class ObservationConfig:
    """Pose observations (a camera's estimate of the object) joining the cost."""

    observation_weight: float = 1.0
    """An observation's weight in the window cost: a world at its 95 % bound scores as much worse
    as the spread of the group's contact costs, so the cost's units do not matter."""
    observation_gate: float = 22.5
    """No world within this Mahalanobis distance squared of a confident observation (6 dof, 0.999)
    re-seeds the group around the observation."""
    inject_share: float = 0.1
    """Share of a group's worlds, the least likely, drawn afresh around a confident observation
    the worlds agree with less than its noise allows (beyond ``inject_gate``, short of
    ``observation_gate``); 0: none. Nothing else moves a group that sits a few noise widths off an
    object at rest."""
    inject_gate: float = 12.59
    """Mahalanobis distance squared of the nearest world beyond which a confident observation
    draws ``inject_share`` of the worlds around itself (6 dof, 0.95)."""
    observation_confident: float = 0.02
    """An observation is confident when its largest position standard deviation is below this [m]."""

    def __post_init__(self) -> None:
        _check(
            self,
            {
                "observation_weight": (0.0, 1e3, ""),
                "observation_gate": (0.0, _INF, ""),
                "inject_share": (0.0, 1.0, ""),
                "inject_gate": (0.0, _INF, ""),
                "observation_confident": (0.0, 1.0, " m"),
            },
        )


TRACKER_GROUPS = {"seeding", "exploration", "contacts", "servos", "estimate", "recovery", "observations"}
"""TrackerConfig's groups of settings other than the optimizer's and the cost's."""


@dataclass(frozen=True)
class TrackerConfig:
    update_every: int = 15
    """T: frames between optimizer updates."""
    seed: int = 0
    """The tracker's random stream."""
    seeding: Seeding = field(default_factory=Seeding)
    exploration: Exploration = field(default_factory=Exploration)
    contacts: ContactExploration = field(default_factory=ContactExploration)
    servos: ServoExploration = field(default_factory=ServoExploration)
    estimate: EstimateConfig = field(default_factory=EstimateConfig)
    recovery: RecoveryConfig = field(default_factory=RecoveryConfig)
    observations: ObservationConfig = field(default_factory=ObservationConfig)
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    cost: CostConfig = field(default_factory=CostConfig)

    def __post_init__(self) -> None:
        _check(self, {"update_every": (1, 10_000, " frames"), "seed": (0, 2**63 - 1, "")})
