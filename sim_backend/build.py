"""The built model: one world of robot + object replicated G x K times into one Newton model, and
the MuJoCo-Warp solver and collision pipeline that step it. Static once built."""

from __future__ import annotations

import contextlib
import logging
import math
import warnings
from collections.abc import Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace

import mujoco_warp as mjw
import newton
import numpy as np
import warp as wp

from .config import DEFAULT_CONE, DEFAULT_IMPRATIO, DEFAULT_INTEGRATOR, PopulationConfig
from .objects import ObjectSpec
from .robots import RobotLayout, RobotSpec, add_robot

__all__ = ["DROPPED", "BuiltModel", "Physics", "build_model", "make_physics", "resolve_physics", "say_timestep"]

log = logging.getLogger(__name__)


DROPPED = ~int(mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS)
"""The bits of a world's overflow mask (newton.solvers.SolverMuJoCo.OverflowBits) that mean its step
left contacts or constraint rows out for want of room: all but the solver's iteration limits, which
share the mask but drop nothing. A step that stops at its iteration budget keeps every contact, and
a fixed budget is how a frame keeps its time."""


@dataclass
class BuiltModel:
    """The replicated model and what one world of it holds."""

    model: newton.Model
    layout: RobotLayout
    """The robot's joints, sensors and limits in one world."""
    object_body: int
    """The object's body index within a world."""
    bodies: int
    """Bodies per world."""
    coords: int
    """Joint coordinates per world (the object's free joint last: 7)."""
    dofs: int
    """Joint DOFs per world."""
    nominal_mass: float
    """The object's mass as built [kg]."""
    nominal_inertia: np.ndarray
    """The object's inertia about its centre of mass as built, (3, 3) [kg m^2]."""


@dataclass
class Physics:
    """What steps the model: the solver, the collision pipeline and their buffers."""

    solver: newton.solvers.SolverMuJoCo
    pipeline: newton.CollisionPipeline
    contacts: newton.Contacts
    observables: object
    """The solver's contact forces, read by the observation kernels."""


def build_model(
    robot: RobotSpec,
    obj: ObjectSpec,
    cfg: PopulationConfig,
    device: wp.context.Device,
    turn: AbstractContextManager | None = None,
) -> BuiltModel:
    """One world of ``robot`` and ``obj``, replicated ``cfg.world_count`` times over a ground plane.
    The composition runs on the host; ``turn`` (if given) is entered only for the upload to ``device``."""
    turn = turn or contextlib.nullcontext()
    world = newton.ModelBuilder()
    newton.solvers.SolverMuJoCo.register_custom_attributes(world)
    # Newton's default detection gap (0.1 m) turns every shape pair within 10 cm into contacts;
    # a few millimetres is plenty at 240 Hz substeps and keeps the buffers small.
    world.rigid_gap = cfg.contact_gap
    layout = add_robot(world, robot)
    object_body = add_object(world, obj)
    builder = newton.ModelBuilder()
    newton.solvers.SolverMuJoCo.register_custom_attributes(builder)
    builder.rigid_gap = cfg.contact_gap
    builder.add_ground_plane()
    builder.replicate(world, cfg.world_count)
    with turn, wp.ScopedDevice(device):
        model = builder.finalize(device=device)
    return BuiltModel(
        model=model,
        layout=layout,
        object_body=object_body,
        bodies=world.body_count,
        coords=world.joint_coord_count,
        dofs=world.joint_dof_count,
        nominal_mass=float(world.body_mass[object_body]),
        nominal_inertia=np.asarray(world.body_inertia[object_body], dtype=np.float32).reshape(3, 3),
    )


def contact_capacity(built: BuiltModel, cfg: PopulationConfig) -> PopulationConfig:
    """``cfg`` with its contact and constraint capacities sized from the robot and object where
    they are None: room for every collision shape of the robot to press the object at two points,
    and the object and the robot to rest on the table at four each, and no less than 32; five
    constraint rows per contact (an elliptic cone's normal and friction rows and the joint limits).
    A world that still makes more drops the excess, and the tracker says so with the numbers."""
    if cfg.contacts_per_world is not None and cfg.constraints_per_world is not None:
        return cfg
    model, w = built.model, built.model.world_count
    flags, body = model.shape_flags.numpy(), model.shape_body.numpy()
    colliding = (flags & int(newton.ShapeFlags.COLLIDE_SHAPES)) != 0
    on_robot = colliding & (body >= 0) & (body % built.bodies != built.object_body)
    robot = int(on_robot.sum()) // max(w, 1)
    contacts = cfg.contacts_per_world or max(32, 2 * robot + 8)
    return replace(cfg, contacts_per_world=contacts, constraints_per_world=cfg.constraints_per_world or 5 * contacts)


def resolve_physics(robot: RobotSpec, cfg: PopulationConfig, layout: RobotLayout | None = None) -> PopulationConfig:
    """``cfg`` with the physics options it leaves open resolved: the friction cone, impratio,
    integrator and collision. Precedence, each later source winning: the defaults (elliptic,
    impratio 10, implicitfast, Newton's collision); the robot's file (``layout.options``: an MJCF's
    ``<option>``, MuJoCo's defaults where it says none, and MuJoCo's collision: what MuJoCo C runs
    it with); the robot config (:class:`.ContactModel`);
    ``cfg``'s own (the service's ``[physics]``, a benchmark's ``--set population.cone``): a
    user's explicit choice wins. A model tuned under MuJoCo's pyramidal cone grips differently
    under an elliptic one."""
    file = layout.options if layout is not None else {}
    cone = cfg.cone or robot.cone or file.get("cone") or DEFAULT_CONE
    impratio = cfg.impratio or robot.impratio or file.get("impratio") or DEFAULT_IMPRATIO
    integrator = cfg.integrator or file.get("integrator") or DEFAULT_INTEGRATOR
    collision = cfg.collision or robot.collision or file.get("collision") or "newton"
    return replace(cfg, cone=cone, impratio=impratio, integrator=integrator, collision=collision)


_SAID: set[tuple] = set()
"""What :func:`_say_once` has said, by key: a population is built per session, and the same
robot and settings would say the same line at every build."""


def _say_once(key: tuple, level: int, message: str, *args: object) -> None:
    """Log ``message`` % ``args`` at ``level`` the first time ``key`` comes, never again."""
    if key not in _SAID:
        _SAID.add(key)
        log.log(level, message, *args)


def say_timestep(name: str, layout: RobotLayout, cfg: PopulationConfig) -> None:
    """Say, once per robot and setting, where the worlds' step differs from the one the robot's file
    was written for by more than a quarter: each frame is ``cfg.substeps`` equal steps, and a servo
    or contact tuned at the file's step behaves otherwise at another (the substeps that come closest
    are named)."""
    file_dt = layout.options.get("timestep")
    dt = cfg.frame_dt / cfg.substeps
    if file_dt is None or abs(dt / file_dt - 1.0) <= 0.25:
        return
    closest = max(2, 2 * round(cfg.frame_dt / file_dt / 2))
    _say_once(
        ("timestep", name, file_dt, dt), logging.INFO,
        "robot '%s': its file steps at %.2f ms, the worlds at %.2f ms (%d substeps of a %g Hz frame);"
        " population.substeps=%d comes closest", name, file_dt * 1e3, dt * 1e3, cfg.substeps, cfg.frame_rate, closest,
    )  # fmt: skip


def make_physics(model: newton.Model, cfg: PopulationConfig, device: wp.context.Device) -> Physics:
    """The MuJoCo-Warp solver with ``cfg``'s budget, and the contacts ``cfg.collision`` names:
    Newton's collision pipeline feeding it, or its own. The pipeline is kept either way: it also
    separates freshly drawn objects from the hand (:mod:`.separate`)."""
    settings = cfg.solver_settings
    if cfg.drop_duplicate_contacts and cfg.collision == "mujoco":
        _say_once(("drop_duplicate_contacts",), logging.WARNING,
                  "population.drop_duplicate_contacts: not used, these worlds collide as MuJoCo does"
                  " (population.collision = 'mujoco'); it acts on Newton's collision pipeline")  # fmt: skip
    with wp.ScopedDevice(device), margins_said():
        solver = newton.solvers.SolverMuJoCo(
            model,
            use_mujoco_contacts=cfg.collision == "mujoco",
            solver=settings.solver,
            integrator=cfg.integrator,
            cone=cfg.cone,
            impratio=cfg.impratio,
            iterations=settings.iterations,
            ls_iterations=settings.ls_iterations,
            jacobian=settings.jacobian,
            tolerance=cfg.tolerance,
            ls_tolerance=cfg.ls_tolerance,
            nconmax=cfg.contacts_per_world,
            njmax=cfg.constraints_per_world,
            # No root is ever switched to kinematic, so no unused weld constraints (two kernels a substep).
            kinematic_switchable_roots=False,
        )
        # Iteration-limit warnings are printf'd from inside kernels, once per world and step;
        # at thousands of worlds they flood the log. Non-converged steps still finish.
        solver.mjw_model.opt.warn_overflow = 0
        pipeline = newton.CollisionPipeline(
            model,
            rigid_contact_max=solver.get_max_contact_count(),
            soft_contact_max=0,
            broad_phase=cfg.broad_phase,
        )
        contacts = pipeline.contacts()
        # Overflow: a per-world bitmask of what the last substep dropped (contacts past nconmax or
        # the pipeline's capacity, constraint rows past njmax), so that no overflow is silent.
        observables = solver.observables(kinds=["contact_f", "overflow"], contacts=contacts)
    return Physics(solver, pipeline, contacts, observables)


@contextlib.contextmanager
def margins_said() -> Iterator[None]:
    """Around building a MuJoCo solver: say in one line what Newton warns once per geom, that under
    MuJoCo's collision the file's geom margins are zeroed (its convex collision takes none), and
    pass on every other warning."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    zeroed = [w for w in caught if "zeroed for NATIVECCD" in str(w.message)]
    for w in caught:
        if w not in zeroed:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if zeroed:
        _say_once(("margins", len(zeroed)), logging.INFO,
                  "%d geoms' margins of the robot's file are zeroed under MuJoCo's collision, which takes "
                  "none in MuJoCo-Warp; population.collision=newton keeps them", len(zeroed))  # fmt: skip


def contact_points(contacts: newton.Contacts) -> list[wp.array]:
    """The contacts' count, shape pairs and first points: the head of every kernel over contacts."""
    c = contacts
    return [c.rigid_contact_count, c.rigid_contact_shape0, c.rigid_contact_shape1, c.rigid_contact_point0]


def add_object(world: newton.ModelBuilder, obj: ObjectSpec) -> int:
    """Add ``obj`` as a free body of ``world``; returns its body index."""
    # The object's friction rules in contacts with the hand (MuJoCo takes the max otherwise).
    attrs = {"mujoco:geom_priority": 1, "mujoco:condim": obj.condim}
    body = world.add_body(label=f"object/{obj.name}")  # comes with a free joint
    start = world.joint_qd_start[world.joint_count - 1]
    world.joint_damping[start : start + 6] = [obj.damping] * 6
    volume = float(abs(obj.mesh.volume))
    cfg = newton.ModelBuilder.ShapeConfig(
        density=obj.mass / volume, mu=obj.friction, mu_torsional=obj.torsional_friction
    )
    if obj.box_half_extents is not None:
        hx, hy, hz = obj.box_half_extents
        world.add_shape_box(body, hx=hx, hy=hy, hz=hz, cfg=cfg, label=obj.name, custom_attributes=attrs)
    elif obj.capsules:
        # Mass comes from the surface mesh's volume; the capsules only collide.
        cfg.density = 0.0
        for i, cap in enumerate(obj.capsules):
            xform, half = _capsule_xform(np.asarray(cap[:3]), np.asarray(cap[3:6]))
            world.add_shape_capsule(body, xform=xform, radius=cap[6], half_height=half, cfg=cfg,
                                    label=f"{obj.name}/{i}", custom_attributes=attrs)  # fmt: skip
        inertia = (obj.mass * np.asarray(obj.mesh.moment_inertia) / abs(obj.mesh.volume)).astype(np.float32)
        world.body_mass[body] = obj.mass
        world.body_inertia[body] = wp.mat33(*inertia.ravel())
    else:
        hull = obj.mesh.convex_hull
        mesh = newton.Mesh(np.asarray(hull.vertices, np.float32), np.asarray(hull.faces, np.int32).ravel())
        world.add_shape_convex_hull(body, mesh=mesh, cfg=cfg, label=obj.name, custom_attributes=attrs)
    return body


def _capsule_xform(p0: np.ndarray, p1: np.ndarray) -> tuple[wp.transform, float]:
    """Transform putting a capsule's z axis from ``p0`` to ``p1``, and its half height."""
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    z = np.array([0.0, 0.0, 1.0])
    cross = np.cross(z, axis / length)
    angle = math.atan2(float(np.linalg.norm(cross)), float(axis[2] / length))
    rot = wp.quat_from_axis_angle(wp.vec3(*(cross / max(np.linalg.norm(cross), 1e-12))), angle)
    return wp.transform(wp.vec3(*(0.5 * (p0 + p1))), rot), 0.5 * length
