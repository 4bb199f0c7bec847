"""The paper's cost, eq. (3), and the touch zones' terms beyond it: how far each simulated world's
observation is from the real robot's.

All twelve terms are batched over groups G, worlds K, sensors L and touch zones Z as torch ops.
Terms whose fields a frame lacks (no force, no slip, no rotational slip: the paper's real robot had
no slip; no touch zones) drop out per group through the ``has_*`` masks. The paper sets the weights
"such that the corresponding mean magnitude of each term is roughly normalized to 1":
:data:`WEIGHTS` are one over each term's mean magnitude measured once in groups that track well, and
fixed. Normalising online by the population's own running means (``CostConfig(weights=None)``) makes
the weights depend on what the worlds get wrong: when most worlds have knocked the object out of the
hand, missed contacts become the common case and cheap, while the force and direction errors of the
few worlds still holding it (terms that only count where contact agrees) are weighed against a mean
near zero. The holding worlds then scored worst and were resampled away (the smoke suite's brick,
frame 74).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from inhand_tracker.sim_backend import Observation
from inhand_tracker.sim_backend.rotations import quat_conjugate, quat_multiply

__all__ = ["TERMS", "TERM_NAMES", "WEIGHTS", "Cost", "CostConfig", "RealObservation", "cost_terms"]

TERM_NAMES = (
    "joints",  # w1 ||q - q_gt||
    "sensor_position",  # w2 sum_l ||P - P_gt||
    "sensor_rotation",  # w3 sum_l angle(R^-1 R_gt)
    "contact_disagree",  # w4 sum_l (1 - alpha)
    "force_magnitude",  # w5 sum_l alpha |dM(c, c_gt)|
    "force_direction",  # w6 sum_l alpha |dphi(c, c_gt)|
    "slip_disagree",  # w7 sum_l (1 - beta)
    "slip_direction",  # w8 sum_l beta |dphi(d, d_gt)|
    "spin_disagree",  # w9 sum_l (1 - gamma)
    "spin_sense",  # w10 sum_l gamma |r - r_gt|
    "zone_disagree",  # w11 sum_z (1 - zeta): touch zones in contact in one and not the other
    "zone_force",  # w12 sum_z zeta |t - t_gt|: normal force error where they agree
)
WEIGHTS = (50.0, 333.0, 25.0, 33.0, 1.7, 6.7, 6.7, 20.0, 6.7, 50.0, 33.0, 1.7)
"""Default w1..w10: one over each term's mean magnitude per frame in groups tracking well (REPS and
PBO on the smoke suite's brick, the running means at the end of the track): joints 0.02 rad,
sensor positions 3 mm, rotations 0.04 rad, 0.03 contact disagreements, force magnitudes 0.6 N,
force directions 0.15 rad, 0.15 slip disagreements, slip directions 0.05 rad, 0.15 spin
disagreements, spin senses 0.02. A missed contact thus costs as much as 20 N of force error. The
touch zones' w11 and w12 are the fingertips' w4 and w5: a zone is a pad that reports its normal force."""

# Smallest running mean a term is normalised by, in its own unit (m, rad, count, N): a term that
# is almost always zero (no slip yet) must not get an enormous weight.
_NORM_FLOOR = torch.tensor([1e-3, 1e-3, 1e-2, 0.05, 0.05, 1e-2, 0.05, 1e-2, 0.05, 0.05, 0.05, 0.05])
TERMS = len(TERM_NAMES)


@dataclass
class RealObservation:
    """What the real robot sensed in one frame, per group; optional fields are zero when absent."""

    q: torch.Tensor
    """Joint positions, (G, D) [rad or m]."""
    sensor_pos: torch.Tensor
    """Sensor positions by forward kinematics of q, (G, L, 3) [m]."""
    sensor_rot: torch.Tensor
    """Sensor orientations by forward kinematics of q, (G, L, 4) quaternion (x, y, z, w)."""
    force: torch.Tensor
    """Contact force on each sensor in its frame, (G, L, 3) [N]."""
    slip: torch.Tensor
    """Translational slip flags, (G, L), 0/1."""
    slip_dir: torch.Tensor
    """Unit slip directions in the sensor's tangent plane, (G, L, 2)."""
    spin: torch.Tensor
    """Rotational slip flags, (G, L), 0/1."""
    spin_sense: torch.Tensor
    """Rotational slip sense, (G, L), 1 counter-clockwise about the pad normal, else 0."""
    touch: torch.Tensor
    """Normal force on each touch zone, (G, Z) [N]."""
    has_force: torch.Tensor
    """Whether the frame carried forces, (G,), 0/1."""
    has_slip: torch.Tensor
    """Whether the frame carried translational slip, (G,), 0/1."""
    has_spin: torch.Tensor
    """Whether the frame carried rotational slip, (G,), 0/1."""
    has_touch: torch.Tensor
    """Whether the frame carried touch zones, (G,), 0/1."""

    @classmethod
    def zeros(cls, g: int, d: int, l: int, device: torch.device, z: int = 0) -> RealObservation:
        o = lambda *s: torch.zeros(s, device=device)  # noqa: E731
        rot = o(g, l, 4)
        rot[..., 3] = 1.0
        fields = (o(g, d), o(g, l, 3), rot, o(g, l, 3), o(g, l), o(g, l, 2), o(g, l), o(g, l), o(g, z))
        return cls(*fields, o(g), o(g), o(g), o(g))


@dataclass(frozen=True)
class CostConfig:
    weights: tuple[float, ...] | None = WEIGHTS
    """Fixed w1..w12; None normalises each term's running mean magnitude over the group's worlds to 1."""
    enabled: tuple[bool, ...] = (True,) * TERMS
    """Switch terms off (ablations: contact terms 4-6, slip terms 7-10, touch zones 11-12)."""
    contact_threshold: float = 0.2
    """A sensor is in contact when its force exceeds this [N]."""
    norm_rate: float = 0.02
    """Running-mean update rate of the normalisation once it has seen 1/rate frames."""

    def __post_init__(self) -> None:
        if self.weights is not None and len(self.weights) != TERMS:
            raise ValueError(f"cost weights: expected {TERMS} values (w1..w{TERMS}), got {len(self.weights)}")
        if len(self.enabled) != TERMS:
            raise ValueError(f"cost enabled: expected {TERMS} flags, got {len(self.enabled)}")


def _angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle [rad] between vectors along the last axis; atan2 form stays accurate near 0 and pi."""
    if a.shape[-1] == 2:
        cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
        return torch.atan2(cross.abs(), (a * b).sum(-1))
    return torch.atan2(torch.linalg.vector_norm(torch.linalg.cross(a, b, dim=-1), dim=-1), (a * b).sum(-1))


def cost_terms(
    sim: Observation, real: RealObservation, contact_threshold: float, touch: tuple[float, float] = (0.0, 0.0)
) -> torch.Tensor:
    """The unweighted terms of eq. (3) and the touch zones' for every world, (G, K, 12). ``touch``:
    the robot's touch deadband and noise's standard deviation [N]: each world's zones read 0 under
    the deadband, as the robot's do, and a zone's force error counts only beyond twice the noise."""
    r = lambda t: t[:, None]  # noqa: E731 - real (G, ...) against sim (G, K, ...)
    joints = torch.linalg.vector_norm(sim.q - r(real.q), dim=-1)
    position = torch.linalg.vector_norm(sim.sensor_pos - r(real.sensor_pos), dim=-1).sum(-1)
    rel = quat_multiply(quat_conjugate(sim.sensor_rot), r(real.sensor_rot).expand_as(sim.sensor_rot))
    rotation = (2.0 * torch.atan2(torch.linalg.vector_norm(rel[..., :3], dim=-1), rel[..., 3].abs())).sum(-1)

    mag_sim = torch.linalg.vector_norm(sim.force, dim=-1)
    mag_real = r(torch.linalg.vector_norm(real.force, dim=-1))
    touch_sim, touch_real = mag_sim > contact_threshold, mag_real > contact_threshold
    alpha = (touch_sim == touch_real).float()
    both = (touch_sim & touch_real).float()
    force_on = r(real.has_force)[..., None]
    contact = (1.0 - alpha).sum(-1) * force_on[..., 0]
    magnitude = (alpha * (mag_sim - mag_real).abs()).sum(-1) * force_on[..., 0]
    direction = (both * _angle_between(sim.force, r(real.force))).sum(-1) * force_on[..., 0]

    beta = (sim.slip == r(real.slip)).float()
    both_slip = sim.slip * r(real.slip)
    slip_on = r(real.has_slip)
    slip = (1.0 - beta).sum(-1) * slip_on
    slip_dir = (both_slip * _angle_between(sim.slip_dir, r(real.slip_dir))).sum(-1) * slip_on

    gamma = (sim.spin == r(real.spin)).float()
    both_spin = sim.spin * r(real.spin)
    spin_on = r(real.has_spin)
    spin = (1.0 - gamma).sum(-1) * spin_on
    sense = (both_spin * (sim.spin_sense - r(real.spin_sense)).abs()).sum(-1) * spin_on
    # Touch zones: each a pad that reports its normal force, compared as the fingertips' magnitudes are.
    # Under the robot's deadband a zone reads 0: compared raw, a world pressing a zone lightly would
    # score worse than one that does not touch it, and selection would move the object away from it.
    deadband, noise = touch
    pressed = torch.where(sim.touch < deadband, 0.0, sim.touch) if deadband > 0 else sim.touch
    zone_sim, zone_real = pressed > contact_threshold, r(real.touch) > contact_threshold
    zeta = (zone_sim == zone_real).float()
    zones_on = r(real.has_touch)
    zones = (1.0 - zeta).sum(-1) * zones_on
    # A difference the sensor's noise makes (within two standard deviations) ranks no world above
    # another: selecting on it walks the population off where the physics holds the object.
    zone_force = (zeta * ((pressed - r(real.touch)).abs() - 2.0 * noise).clamp_min(0.0)).sum(-1) * zones_on
    terms = [joints, position, rotation, contact, magnitude, direction, slip, slip_dir, spin, sense, zones, zone_force]
    return torch.stack(terms, dim=-1)


@dataclass
class Cost:
    """Eq. (3) with its weights; under the online normalisation (``weights=None``) it keeps each
    term's running mean magnitude."""

    config: CostConfig
    groups: int
    device: torch.device
    running: torch.Tensor = field(init=False)
    """Running mean magnitude of each term, (G, 12), in the term's unit (online normalisation only)."""
    frames: torch.Tensor = field(init=False)
    """Frames each group's running means have seen, (G,) float64 on the device: a device counter,
    so that a captured frame graph advances it on every replay."""
    enabled: torch.Tensor | None = None
    """Terms switched on per group, (G, 12) bool (ablations run as groups); default config.enabled."""
    touch: tuple[float, float] = (0.0, 0.0)
    """The robot's touch deadband and noise's standard deviation [N] (``touch_deadband``, ``touch_noise``)."""
    last_terms: torch.Tensor | None = field(init=False, default=None)
    """The unweighted terms of the latest frame, (G, K, 12)."""

    def __post_init__(self) -> None:
        self.running = torch.zeros(self.groups, TERMS, device=self.device)
        self.frames = torch.zeros(self.groups, dtype=torch.float64, device=self.device)
        self._floor = _NORM_FLOOR.to(self.device)
        enabled = self.config.enabled if self.enabled is None else self.enabled
        self._enabled = torch.as_tensor(enabled, dtype=torch.float32, device=self.device).expand(self.groups, TERMS)
        fixed = self.config.weights
        self._fixed = None if fixed is None else torch.tensor(fixed, dtype=torch.float32, device=self.device)

    def weights(self) -> torch.Tensor:
        """Current w1..w12 per group, (G, 12)."""
        if self._fixed is not None:
            return self._fixed * self._enabled
        return self._enabled / torch.maximum(self.running, self._floor)

    def __call__(self, sim: Observation, real: RealObservation) -> torch.Tensor:
        """Weighted cost of every world, (G, K); updates the running term magnitudes when they weigh."""
        terms = cost_terms(sim, real, self.config.contact_threshold, self.touch)
        self.last_terms = terms
        if self._fixed is None:  # fixed weights need no running means: nothing more per frame
            self.frames += 1
            rate = (1.0 / self.frames).clamp_(min=self.config.norm_rate).float()
            self.running.lerp_(terms.mean(dim=1), rate[:, None])
        return (terms * self.weights()[:, None, :]).sum(-1)

    def reset(self, groups: torch.Tensor) -> None:
        """Forget the running term magnitudes of ``groups`` (G,) bool: a new track starts there."""
        self.running.masked_fill_(groups[:, None], 0.0)
        self.frames.masked_fill_(groups, 0.0)
