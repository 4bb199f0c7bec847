"""A population's settings: size, stepping, the solver's budget and the sensing thresholds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import warp as wp

from inhand_tracker.protocol import DEFAULT_WORLDS

__all__ = [
    "DEFAULT_CONE",
    "DEFAULT_IMPRATIO",
    "DEFAULT_INTEGRATOR",
    "PopulationConfig",
    "SolverSettings",
    "forward_only_kernels",
    "resolve_device",
]


DEFAULT_CONE = "elliptic"
"""The friction cone where neither the robot nor the user names one: accurate sticking."""
DEFAULT_IMPRATIO = 10.0
"""The impratio where neither the robot nor the user names one: stiff sticking contacts."""
DEFAULT_INTEGRATOR = "implicitfast"
"""The integrator where neither the robot's file nor the user names one: the servos' damping
treated implicitly."""


@dataclass(frozen=True)
class PopulationConfig:
    """Size, stepping and sensing settings of a population."""

    groups: int = 1
    """G: independent tracks stepped together."""
    worlds: int = DEFAULT_WORLDS
    """K: worlds per group."""
    substeps: int = 8
    """Physics substeps per control frame; even, so the state buffers come back to the captured ones."""
    frame_rate: float = 30.0
    """Control frames per second [Hz]."""
    ramp_targets: bool = True
    """Move each joint's target linearly from the last frame's to this frame's across the
    substeps, as a real position controller interpolates between commands. Off, the target steps
    at the frame boundary and the stiff wrist jerks there, where engines disagree most
    (docs/benchmarks.md)."""
    device: str = "auto"
    """"auto" (CUDA when present, else CPU), "cpu", "cuda" or "cuda:N"."""
    use_graph: bool = True
    """Replay a captured graph per frame (False steps eagerly, for debugging)."""
    solver: str = "auto"
    """MuJoCo constraint solver: "newton", "cg", or "auto" (Newton). Newton converges in a few
    iterations where CG needs tens; each Newton iteration assembles and factors a Hessian, which
    the sparse Jacobian keeps cheap (docs/benchmarks.md)."""
    integrator: str | None = None
    """MuJoCo integrator: "implicitfast" treats the joint PD damping implicitly, "euler"; None: the
    robot file's, else implicitfast (:func:`.build.resolve_physics` states the precedence)."""
    cone: str | None = None
    """Friction cone: "elliptic" (accurate sticking) or "pyramidal"; None: the robot's, else
    elliptic (:func:`.build.resolve_physics` states the precedence)."""
    impratio: float | None = None
    """Frictional-to-normal impedance ratio; above 1 makes sticking contacts stiffer. None: the
    robot's, else 10."""
    iterations: int | None = None
    """Solver iterations; None: 20 for Newton, 40 for CG."""
    ls_iterations: int | None = None
    """Line-search iterations; None: 10 for Newton, 6 for CG."""
    jacobian: str = "sparse"
    """Constraint Jacobian layout: "dense" or "sparse". A contact row touches the wrist, one finger
    and the object, about half of the DOFs, so the sparse Hessian products do about half the work
    (docs/benchmarks.md)."""
    tolerance: float = 1e-4
    """Solver convergence tolerance on the scaled cost improvement and gradient. Looser than the
    solver's own 1e-6 (with ``ls_tolerance`` 0.1 against its 0.01): faster, at no accuracy the
    paired benchmarks can tell (docs/real-time.md). Ground truth keeps the solver's own."""
    ls_tolerance: float = 0.1
    """Line-search tolerance: the search stops once the slope has fallen to this share of its start."""
    contacts_per_world: int | None = None
    """MuJoCo contact capacity per world (nconmax); None sizes it from the robot and object
    (:func:`sim_backend.build.contact_capacity`): a pinch makes few, an object rolled on a
    palm among curled fingers many."""
    broad_phase: str = "explicit"
    """Collision broad phase: "explicit" tests the model's precomputed shape pairs (the hand never
    collides with itself, so that list is short), "sap" or "nxn" search all shapes."""
    contact_gap: float = 0.005
    """Shapes closer than this make (speculative) contacts [m]."""
    drop_duplicate_contacts: bool = False
    """Make a contact that Newton's narrow phase writes twice (same shapes, points and normal)
    count once, as MuJoCo C does (:mod:`.duplicates`). Newton's collision only."""
    collision: str | None = None
    """Who finds the contacts: "mujoco" (MuJoCo-Warp's own collision, as MuJoCo C collides the
    file it was written for) or "newton" (Newton's collision pipeline, with ``broad_phase`` and
    ``drop_duplicate_contacts``); None: the robot's, else "mujoco" for a robot from an MJCF and
    "newton" for the rest (:func:`.build.resolve_physics`). Both detect within ``contact_gap``; the
    touch sensing reads either's contacts and forces."""
    constraints_per_world: int | None = None
    """MuJoCo constraint rows per world (njmax); None: five per contact the world holds."""
    slip_speed: float = 0.01
    """Tangential speed of a pad against the object above which it slips [m/s]."""
    spin_speed: float = 0.3
    """Spin of a pad against the object about the pad normal above which it slips [rad/s]."""
    lost_distance: float = 0.35
    """An object farther than this from the centre of the sensors is away from the hand [m]
    (``HEALTH_AWAY``): lost while the real hand holds it."""
    lost_speed: float = 5.0
    """An object faster than this has exploded [m/s]."""
    floor_z: float = -0.05
    """An object below this height has fallen through the table [m]."""
    seed: int = 0

    def __post_init__(self) -> None:
        counts = (
            "groups",
            "worlds",
            "substeps",
            "iterations",
            "ls_iterations",
            "contacts_per_world",
            "constraints_per_world",
        )
        for name in counts:
            value = getattr(self, name)
            if value is None and name.endswith(("iterations", "per_world")):
                continue
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"population.{name}: expected a positive integer, got {value!r}")
        if self.substeps % 2:
            raise ValueError(f"population.substeps: expected an even number, got {self.substeps}")
        if self.solver not in ("auto", "newton", "cg"):
            raise ValueError(f"population.solver: expected 'auto', 'newton' or 'cg', got {self.solver!r}")
        if self.jacobian not in ("dense", "sparse"):
            raise ValueError(f"population.jacobian: expected 'dense' or 'sparse', got {self.jacobian!r}")
        for name in ("tolerance", "ls_tolerance"):
            if not (0.0 < getattr(self, name) < 1.0):
                raise ValueError(f"population.{name}: expected 0 < {name} < 1, got {getattr(self, name)}")
        if not (0.0 < self.frame_rate <= 1000.0):
            raise ValueError(f"population.frame_rate: expected 0 < rate <= 1000 Hz, got {self.frame_rate}")
        if self.collision not in (None, "newton", "mujoco"):
            raise ValueError(f"population.collision: expected 'newton' or 'mujoco', got {self.collision!r}")
        # Settable from `bench accuracy --set population.NAME`: a zero or negative one would make
        # MuJoCo's friction singular or flag every world lost, far from where it was set.
        if self.cone not in (None, "pyramidal", "elliptic"):
            raise ValueError(f"population.cone: expected 'pyramidal' or 'elliptic', got {self.cone!r}")
        for name in ("impratio", "slip_speed", "spin_speed", "lost_distance", "lost_speed"):
            if getattr(self, name) is not None and not getattr(self, name) > 0.0:
                raise ValueError(f"population.{name}: expected > 0, got {getattr(self, name)}")
        if not self.contact_gap >= 0.0:
            raise ValueError(f"population.contact_gap: expected >= 0 m, got {self.contact_gap}")

    @property
    def world_count(self) -> int:
        return self.groups * self.worlds

    @property
    def frame_dt(self) -> float:
        return 1.0 / self.frame_rate

    @property
    def solver_settings(self) -> SolverSettings:
        """The solver as it runs: "auto" resolved and the default iteration counts filled in."""
        solver = self.solver if self.solver != "auto" else "newton"
        iterations, ls_iterations = (20, 10) if solver == "newton" else (40, 6)
        return SolverSettings(solver, self.jacobian, self.iterations or iterations, self.ls_iterations or ls_iterations)


class SolverSettings(NamedTuple):
    """A population's constraint solver as it runs."""

    solver: str
    jacobian: str
    iterations: int
    ls_iterations: int

    @property
    def name(self) -> str:
        """E.g. "newton/sparse", as the benchmark tables show it."""
        return f"{self.solver}/{self.jacobian}"


def resolve_device(name: str = "auto") -> wp.context.Device:
    """The Warp device for ``name``; "auto" picks CUDA when present, else the CPU."""
    if name == "auto":
        return wp.get_device("cuda:0" if wp.is_cuda_available() else "cpu")
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(f"population.device: '{name}' requested but no CUDA device is available")
    try:
        return wp.get_device(name)
    except Exception as exc:
        raise ValueError(f"population.device: unknown device '{name}' (expected auto, cpu, cuda or cuda:N)") from exc


def forward_only_kernels() -> None:
    """Have Warp compile no adjoints for the modules that do not choose (Newton's; MuJoCo-Warp's
    and ours already opt out). Nothing here differentiates through the physics, and a first start
    compiles about a quarter less, with bit-identical physics. Warp reads the setting when a
    kernel module is imported, so importing this package runs it before it imports newton."""
    import warp as wp

    wp.config.enable_backward = False
