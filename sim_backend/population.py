"""The population: G groups x K worlds of hand + object in one Newton model, stepped as one graph.

World ``w = g * K + k`` is world ``k`` of group ``g``. Every per-world quantity is exposed as a
torch view of the Warp array it lives in (``wp.to_torch``, no copy), shaped (G, K, ...), so the
tracker's cost and resampling are torch ops on the simulation's own memory.

One control frame (all substeps, the collision pipeline, the observation kernels) is captured
once as a graph and replayed by :meth:`Population.step`, on CUDA and on Warp's CPU device alike.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import NamedTuple

import newton
import numpy as np
import torch
import warp as wp

from protocol import DEFAULT_WORLDS

from . import observe
from .objects import ObjectSpec
from .robots import RobotLayout, RobotSpec, add_robot
from .rotations import quat_exp, quat_multiply

__all__ = ["Population", "PopulationConfig", "SolverSettings", "resolve_device"]


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
    device: str = "auto"
    """"auto" (CUDA when present, else CPU), "cpu", "cuda" or "cuda:N"."""
    use_graph: bool = True
    """Replay a captured graph per frame (False steps eagerly, for debugging)."""
    solver: str = "auto"
    """MuJoCo constraint solver: "newton", "cg", or "auto" (Newton). Newton converges in 1-8
    iterations where CG needs 10-40 (a quarter of CG's steps stop at 40 unconverged); each
    Newton iteration assembles and factors a Hessian, which the sparse Jacobian keeps cheap on
    the CPU (K=40 on 2 cores, the hand in motion: 49 ms of physics per frame against CG's 94;
    docs/benchmarks.md)."""
    integrator: str = "implicitfast"
    """MuJoCo integrator: "implicitfast" treats the joint PD damping implicitly, or "euler"."""
    cone: str = "elliptic"
    """Friction cone: "elliptic" (accurate sticking) or "pyramidal"."""
    impratio: float = 10.0
    """Frictional-to-normal impedance ratio; above 1 makes sticking contacts stiffer."""
    iterations: int | None = None
    """Solver iterations; None: 20 for Newton, 40 for CG."""
    ls_iterations: int | None = None
    """Line-search iterations; None: 10 for Newton, 6 for CG."""
    jacobian: str = "sparse"
    """Constraint Jacobian layout: "dense" or "sparse". A contact row touches the wrist, one finger
    and the object, about half of the DOFs, so the sparse Hessian products do half the work: on an
    H100 at K=4096, 4 substeps, 10.2 ms a frame against dense's 13.5; on the 2-core CPU at K=40,
    8 substeps, 49 against 85 (docs/benchmarks.md)."""
    tolerance: float = 1e-6
    """Solver convergence tolerance on the scaled cost improvement and gradient."""
    contacts_per_world: int = 32
    """MuJoCo contact capacity per world (nconmax); a held grasp makes ~10, a grasp on the table ~20."""
    broad_phase: str = "explicit"
    """Collision broad phase: "explicit" tests the model's precomputed shape pairs (the hand never
    collides with itself, so that list is short), "sap" or "nxn" search all shapes."""
    contact_gap: float = 0.005
    """Shapes closer than this make (speculative) contacts [m]."""
    constraints_per_world: int = 160
    """MuJoCo constraint rows per world (njmax)."""
    slip_speed: float = 0.01
    """Tangential speed of a pad against the object above which it slips [m/s]."""
    spin_speed: float = 0.3
    """Spin of a pad against the object about the pad normal above which it slips [rad/s]."""
    lost_distance: float = 0.35
    """An object farther than this from the centre of the sensors is lost [m]."""
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
            if value is None and name.endswith("iterations"):
                continue
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"population {name}: expected a positive integer, got {value!r}")
        if self.substeps % 2:
            raise ValueError(f"population substeps: expected an even number, got {self.substeps}")
        if self.solver not in ("auto", "newton", "cg"):
            raise ValueError(f"population solver: expected 'auto', 'newton' or 'cg', got {self.solver!r}")
        if self.jacobian not in ("dense", "sparse"):
            raise ValueError(f"population jacobian: expected 'dense' or 'sparse', got {self.jacobian!r}")
        if not (0.0 < self.tolerance < 1.0):
            raise ValueError(f"population tolerance: expected 0 < tolerance < 1, got {self.tolerance}")
        if not (0.0 < self.frame_rate <= 1000.0):
            raise ValueError(f"population frame_rate: expected 0 < rate <= 1000 Hz, got {self.frame_rate}")
        # Settable from `bench accuracy --set population.NAME`: a zero or negative one would make
        # MuJoCo's friction singular or flag every world lost, far from where it was set.
        for name in ("impratio", "slip_speed", "spin_speed", "lost_distance", "lost_speed"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"population {name}: expected > 0, got {getattr(self, name)}")
        if not self.contact_gap >= 0.0:
            raise ValueError(f"population contact_gap: expected >= 0 m, got {self.contact_gap}")

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
        raise ValueError(f"population device: '{name}' requested but no CUDA device is available")
    try:
        return wp.get_device(name)
    except Exception as exc:
        raise ValueError(f"population device: unknown device '{name}'") from exc


def _capsule_xform(p0: np.ndarray, p1: np.ndarray) -> tuple[wp.transform, float]:
    """Transform putting a capsule's z axis from ``p0`` to ``p1``, and its half height."""
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    z = np.array([0.0, 0.0, 1.0])
    cross = np.cross(z, axis / length)
    angle = math.atan2(float(np.linalg.norm(cross)), float(axis[2] / length))
    rot = wp.quat_from_axis_angle(wp.vec3(*(cross / max(np.linalg.norm(cross), 1e-12))), angle)
    return wp.transform(wp.vec3(*(0.5 * (p0 + p1))), rot), 0.5 * length


@wp.kernel(enable_backward=False)
def _apply_wrench(
    wrench: wp.array[wp.spatial_vector],
    bodies_per_world: int,
    object_body: int,
    body_f0: wp.array[wp.spatial_vector],
    body_f1: wp.array[wp.spatial_vector],
):
    # Both state buffers: substeps alternate between them.
    w = wp.tid()
    b = w * bodies_per_world + object_body
    body_f0[b] = wrench[w]
    body_f1[b] = wrench[w]


class Population:
    """G x K worlds of one robot and one object type, stepped in lock-step.

    Typical frame: :meth:`set_targets` with the robot's controls, then :meth:`step`; read
    :attr:`obs`. Between frames: :meth:`resample`, :meth:`set_params`, :meth:`set_wrench`.
    """

    def __init__(self, robot: RobotSpec, obj: ObjectSpec, config: PopulationConfig | None = None):
        self.config = cfg = config or PopulationConfig()
        self.device = resolve_device(cfg.device)
        self.robot_spec = robot
        self.object = obj
        self.G, self.K, self.W = cfg.groups, cfg.worlds, cfg.world_count
        torch_device = wp.device_to_torch(self.device)
        self.torch_device = torch.device(torch_device)
        self._torch_stream = wp.stream_to_torch(self.device.stream) if self.device.is_cuda else None

        world = newton.ModelBuilder()
        newton.solvers.SolverMuJoCo.register_custom_attributes(world)
        # Newton's default detection gap (0.1 m) turns every shape pair within 10 cm into contacts;
        # a few millimetres is plenty at 240 Hz substeps and keeps the buffers small.
        world.rigid_gap = cfg.contact_gap
        self.layout: RobotLayout = add_robot(world, robot)
        self._object_body = self._add_object(world, obj)
        self.D, self.L = self.layout.dof_count, self.layout.sensor_count

        builder = newton.ModelBuilder()
        newton.solvers.SolverMuJoCo.register_custom_attributes(builder)
        builder.rigid_gap = cfg.contact_gap
        builder.add_ground_plane()
        builder.replicate(world, self.W)
        with wp.ScopedDevice(self.device):
            self.model = builder.finalize(device=self.device)
        self._bodies = world.body_count
        self._coords = world.joint_coord_count
        self._dofs = world.joint_dof_count
        self._nominal_mass = float(world.body_mass[self._object_body])
        inertia = torch.tensor(np.asarray(world.body_inertia[self._object_body]), dtype=torch.float32).reshape(3, 3)
        # Kept on the device: set_params runs inside the tracker's captured update, where a host
        # copy or a checked inverse would stall or break the capture.
        self._nominal_inertia = inertia.to(self.torch_device)
        self._nominal_inv_inertia = torch.linalg.inv(inertia).to(self.torch_device)

        settings = cfg.solver_settings
        with wp.ScopedDevice(self.device):
            self.solver = newton.solvers.SolverMuJoCo(
                self.model,
                use_mujoco_contacts=False,
                solver=settings.solver,
                integrator=cfg.integrator,
                cone=cfg.cone,
                impratio=cfg.impratio,
                iterations=settings.iterations,
                ls_iterations=settings.ls_iterations,
                jacobian=settings.jacobian,
                tolerance=cfg.tolerance,
                nconmax=cfg.contacts_per_world,
                njmax=cfg.constraints_per_world,
            )
            # Iteration-limit warnings are printf'd from inside kernels, once per world and step;
            # at thousands of worlds they flood the log. Non-converged steps still finish.
            self.solver.mjw_model.opt.warn_overflow = 0
            self.pipeline = newton.CollisionPipeline(
                self.model,
                rigid_contact_max=self.solver.get_max_contact_count(),
                soft_contact_max=0,
                broad_phase=cfg.broad_phase,
            )
            self.contacts = self.pipeline.contacts()
            self._observables = self.solver.observables(kinds=["contact_f"], contacts=self.contacts)
            self.state_0 = self.model.state()
            self.state_1 = self.model.state()
            self.control = self.model.control()
            self._buf = observe.allocate_buffers(self.W, self.D, self.L)
            self._static = self._static_arrays()

        self._views()
        self.obs = observe.observation_views(self._buf, self.G, self.K)
        self.reset_state()
        self.set_params(
            mass=torch.full((self.G, self.K), obj.mass), friction=torch.full((self.G, self.K), obj.friction)
        )
        self.set_targets(np.broadcast_to(self.layout.default_q, (self.G, self.D)))
        self._graph = None
        if cfg.use_graph:
            self._capture()

    # ------------------------------------------------------------------ build
    def _add_object(self, world: newton.ModelBuilder, obj: ObjectSpec) -> int:
        # The object's friction rules in contacts with the hand (MuJoCo takes the max otherwise).
        attrs = {"mujoco:geom_priority": 1}
        body = world.add_body(label=f"object/{obj.name}")  # comes with a free joint
        volume = float(abs(obj.mesh.volume))
        cfg = newton.ModelBuilder.ShapeConfig(density=obj.mass / volume, mu=obj.friction)
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

    def _static_arrays(self) -> dict[str, wp.array]:
        lay, W, nb = self.layout, self.W, self._bodies
        sensor_row = np.full(self.model.body_count, -1, np.int32)
        object_world = np.full(self.model.body_count, -1, np.int32)
        worlds = np.arange(W)
        for l, b in enumerate(lay.sensor_bodies):
            sensor_row[worlds * nb + b] = worlds * self.L + l
        object_world[worlds * nb + self._object_body] = worlds
        offsets = [wp.transform(wp.vec3(*o[:3]), wp.quat(*o[3:])) for o in lay.sensor_offsets]
        return {
            "coord_index": wp.array(lay.coord_indices.astype(np.int32), dtype=wp.int32),
            "sensor_body": wp.array(lay.sensor_bodies.astype(np.int32), dtype=wp.int32),
            "sensor_offset": wp.array(offsets, dtype=wp.transform),
            "sensor_row": wp.array(sensor_row, dtype=wp.int32),
            "object_world": wp.array(object_world, dtype=wp.int32),
        }

    def _views(self) -> None:
        """Torch views (no copies) of the per-world simulation arrays, leading axes (G, K)."""
        G, K, nb = self.G, self.K, self._bodies
        t = wp.to_torch
        self._state_views = {
            "joint_q": lambda s: t(s.joint_q).view(G, K, self._coords),
            "joint_qd": lambda s: t(s.joint_qd).view(G, K, self._dofs),
            "body_q": lambda s: t(s.body_q).view(G, K, nb * 7),
            "body_qd": lambda s: t(s.body_qd).view(G, K, nb * 6),
        }
        self._warmstart = t(self.solver.mjw_data.qacc_warmstart).view(G, K, -1)
        # Position targets live in joint-coordinate layout, like joint_q.
        dof = self.layout.coord_indices
        targets = t(self.control.joint_target_q).view(G, K, self._coords)
        contiguous = np.array_equal(dof, np.arange(dof[0], dof[0] + len(dof)))
        self._target_view = targets[..., dof[0] : dof[0] + len(dof)] if contiguous else None
        self._targets_all = targets
        self._target_index = torch.as_tensor(dof, device=self.torch_device)
        self._target_stage = torch.zeros((G, self.D), dtype=torch.float32, device=self.torch_device)
        self._lower = torch.as_tensor(self.layout.lower, dtype=torch.float32, device=self.torch_device)
        self._upper = torch.as_tensor(self.layout.upper, dtype=torch.float32, device=self.torch_device)
        o = self._object_body
        self._mass = t(self.model.body_mass)[o::nb].view(G, K)
        self._inv_mass = t(self.model.body_inv_mass)[o::nb].view(G, K)
        self._inertia = t(self.model.body_inertia)[o::nb].view(G, K, 3, 3)
        self._inv_inertia = t(self.model.body_inv_inertia)[o::nb].view(G, K, 3, 3)
        # The object's shapes sit at the same offset in every world: view them as (W, n).
        shape_body = self.model.shape_body.numpy()
        obj_shapes = np.flatnonzero((shape_body >= 0) & (shape_body % nb == o)).reshape(self.W, -1)
        per_world = int(obj_shapes[1, 0] - obj_shapes[0, 0]) if self.W > 1 else 0
        expected = obj_shapes[0] + per_world * np.arange(self.W)[:, None]
        if not np.array_equal(obj_shapes, expected) or np.any(np.diff(obj_shapes[0]) != 1):
            raise ValueError("object shapes: expected the same contiguous shapes in every world")
        mu = t(self.model.shape_material_mu)
        n = obj_shapes.shape[1]
        self._shape_mu = torch.as_strided(mu, (G, K, n), (K * per_world, per_world, 1), int(obj_shapes[0, 0]))
        self._friction = self._shape_mu[..., 0]
        self._wrench = t(self._buf.wrench).view(G, K, 6)
        self._solver_inertia_views()

    def _solver_inertia_views(self) -> None:
        """Views of the MuJoCo-Warp fields that the object's mass sets, with their nominal values.

        Newton's notify_model_changed(BODY_INERTIAL_PROPERTIES) re-runs MuJoCo's set_const on every
        world (kinematics, composite inertia, a factorisation: 8.5 ms at K=40 on an H100, inside the
        update every T frames). The object is a free body whose inertia scales with its mass, so
        every constant it changes scales exactly: mass, principal inertia and subtree mass by s =
        m / m0, the inverse weights of the body and its six DOFs by 1 / s, the world's subtree mass
        by m - m0. Writing those directly gives set_const's values to float rounding (checked in
        tests/test_population.py) in a handful of torch ops."""
        G, K, t, mjm = self.G, self.K, wp.to_torch, self.solver.mjw_model
        body = int(np.flatnonzero(self.solver.mjc_body_to_newton.numpy()[0] == self._object_body)[0])
        dofs = np.flatnonzero(mjm.dof_bodyid.numpy() == body)
        if len(dofs) != 6 or np.any(np.diff(dofs) != 1):
            raise ValueError(f"object body: expected 6 contiguous solver DOFs, got {dofs.tolist()}")
        self._mj = {
            "mass": t(mjm.body_mass).view(G, K, -1)[..., body],
            "inertia": t(mjm.body_inertia).view(G, K, -1, 3)[..., body, :],
            "subtree": t(mjm.body_subtreemass).view(G, K, -1)[..., body],
            "root_subtree": t(mjm.body_subtreemass).view(G, K, -1)[..., 0],
            "invweight": t(mjm.body_invweight0).view(G, K, -1, 2)[..., body, :],
            "dof_invweight": t(mjm.dof_invweight0).view(G, K, -1)[..., dofs[0] : dofs[-1] + 1],
        }
        self._mj0 = {name: view.clone() for name, view in self._mj.items()}

    # ------------------------------------------------------------------ frame
    def _simulate(self) -> None:
        """One control frame: wrench, substeps, observation. Captured once, replayed per frame."""
        cfg, b, s = self.config, self._buf, self._static
        wp.launch(
            _apply_wrench,
            dim=self.W,
            inputs=[b.wrench, self._bodies, self._object_body],
            outputs=[self.state_0.body_f, self.state_1.body_f],
        )
        dt = cfg.frame_dt / cfg.substeps
        for i in range(cfg.substeps):
            s_in, s_out = (self.state_0, self.state_1) if i % 2 == 0 else (self.state_1, self.state_0)
            self.pipeline.collide(s_in, self.contacts)
            self.solver.step(s_in, s_out, self.control, self.contacts, dt, observables=self._observables)
        b.wrench.zero_()  # a perturbation lasts one frame
        st = self.state_0
        wp.launch(observe.gather_joints, dim=(self.W, self.D), inputs=[st.joint_q, self._coords, s["coord_index"]],
                  outputs=[b.q])  # fmt: skip
        wp.launch(
            observe.sensor_poses,
            dim=(self.W, self.L),
            inputs=[st.body_q, self._bodies, s["sensor_body"], s["sensor_offset"]],
            outputs=[b.sensor_pos, b.sensor_rot, b.force_acc, b.slip_acc, b.spin_acc, b.weight_acc],
        )
        c = self.contacts
        wp.launch(
            observe.accumulate_contacts,
            dim=c.rigid_contact_max,
            inputs=[
                c.rigid_contact_count,
                c.rigid_contact_shape0,
                c.rigid_contact_shape1,
                c.rigid_contact_point0,
                c.rigid_contact_normal,
                self._observables.contact_f,
                self.model.shape_body,
                st.body_q,
                st.body_qd,
                self.model.body_com,
                s["sensor_row"],
                s["object_world"],
                self.L,
            ],
            outputs=[b.force_acc, b.slip_acc, b.spin_acc, b.weight_acc],
        )
        observe.launch_finish(b, cfg.slip_speed, cfg.spin_speed)
        wp.launch(
            observe.object_health,
            dim=self.W,
            inputs=[
                st.body_q,
                st.body_qd,
                st.joint_q,
                self._bodies,
                self._coords,
                self._object_body,
                b.sensor_pos,
                self.L,
                cfg.floor_z,
                cfg.lost_distance,
                cfg.lost_speed,
            ],
            outputs=[b.object_pose, b.health],
        )

    def _capture(self) -> None:
        with wp.ScopedDevice(self.device):
            # Compile every kernel once outside capture, then record; the eager frame is undone.
            saved = self._snapshot()
            self._simulate()
            self._restore(saved)
            with wp.ScopedCapture(device=self.device) as capture:
                self._simulate()
            self._graph = capture.graph

    def _state_tensors(self) -> list[torch.Tensor]:
        """Every tensor that carries a world's dynamic state from one frame to the next."""
        views = [view(s) for s in (self.state_0, self.state_1) for view in self._state_views.values()]
        return [*views, self._warmstart]

    def _snapshot(self) -> list[torch.Tensor]:
        with self.on_stream():
            return [t.clone() for t in self._state_tensors()]

    def _restore(self, saved: list[torch.Tensor]) -> None:
        with self.on_stream():
            for t, s in zip(self._state_tensors(), saved, strict=True):
                t.copy_(s)

    def step(self) -> None:
        """Advance every world by one control frame (one graph replay).

        Called while an enclosing graph is being captured on the device (the tracker's frame), it
        launches the frame's kernels into that capture instead."""
        with wp.ScopedDevice(self.device):
            if self._graph is not None and not self.device.is_capturing:
                wp.capture_launch(self._graph)
            else:
                self._simulate()

    def step_eager(self) -> None:
        """The same frame launched kernel by kernel (for checking the graph)."""
        with wp.ScopedDevice(self.device):
            self._simulate()

    @contextlib.contextmanager
    def on_stream(self):
        """Run torch work on Warp's stream so it is ordered with the graph replays."""
        if self._torch_stream is None:
            yield
        else:
            with torch.cuda.stream(self._torch_stream):
                yield

    # ------------------------------------------------------------------ inputs
    def set_targets(self, targets: np.ndarray | torch.Tensor) -> None:
        """Joint position targets per group, shape (G, D) [rad or m], clipped to the joint limits."""
        arr = np.asarray(targets.cpu() if isinstance(targets, torch.Tensor) else targets, dtype=np.float32)
        if arr.shape != (self.G, self.D):
            raise ValueError(f"targets: expected shape ({self.G}, {self.D}), got {arr.shape}")
        bad = ~np.isfinite(arr)
        if bad.any():
            g, d = np.argwhere(bad)[0]
            raise ValueError(
                f"targets: {int(bad.sum())} non-finite values, first at group {g} joint "
                f"'{self.layout.joint_names[d]}' = {arr[g, d]}"
            )
        self._write_targets(torch.from_numpy(arr))

    def _write_targets(self, targets: torch.Tensor) -> None:
        """:meth:`set_targets` for targets already checked, (G, D): no host work, so it can run
        inside a captured graph (the tracker's frame)."""
        with self.on_stream():
            self._target_stage.copy_(targets, non_blocking=True)
            torch.clamp(self._target_stage, self._lower, self._upper, out=self._target_stage)
            if self._target_view is not None:
                self._target_view.copy_(self._target_stage[:, None, :].expand(self.G, self.K, self.D))
            else:
                self._targets_all[..., self._target_index] = self._target_stage[:, None, :]

    def set_wrench(self, wrench: torch.Tensor) -> None:
        """Perturbation wrench on each world's object for the next frame, shape (G, K, 6):
        force [N] then torque [N m], world frame, at the centre of mass."""
        if tuple(wrench.shape) != (self.G, self.K, 6):
            raise ValueError(f"wrench: expected shape ({self.G}, {self.K}, 6), got {tuple(wrench.shape)}")
        with self.on_stream():
            self._wrench.copy_(wrench, non_blocking=True)

    def reset_state(
        self,
        object_pose: np.ndarray | torch.Tensor | None = None,
        joint_q: np.ndarray | torch.Tensor | None = None,
        groups: np.ndarray | torch.Tensor | None = None,
    ) -> None:
        """Put worlds at rest with their object at ``object_pose`` and their robot at ``joint_q``.

        object_pose: shape (G, K, 7) or (G, 7) or (7,): position [m], quaternion (x, y, z, w); the
        quaternion is normalised. Default: on the table in front of the robot.
        joint_q: shape (G, K, D), (G, D) or (D,) [rad or m]; default the robot's start pose.
        groups: (G,) bool, the groups to reset (default all); the others are left untouched.
        """
        if object_pose is None:
            z = -float(self.object.mesh.bounds[0, 2])
            object_pose = np.array([0.1, 0.0, z, 0.0, 0.0, 0.0, 1.0])
        pose = self._check("object_pose", object_pose, 7)
        norm = torch.linalg.vector_norm(pose[..., 3:], dim=-1, keepdim=True)
        if bool((norm < 1e-6).any()):
            raise ValueError("object_pose: quaternion (x, y, z, w) of zero length")
        pose = torch.cat([pose[..., :3], pose[..., 3:] / norm], dim=-1).to(self.torch_device)
        q = self._check("joint_q", self.layout.default_q if joint_q is None else joint_q, self.D)
        q = torch.clamp(q.to(self.torch_device), self._lower, self._upper)
        if groups is None:
            groups = torch.ones(self.G, dtype=torch.bool)
        groups = torch.as_tensor(
            np.asarray(groups.cpu() if isinstance(groups, torch.Tensor) else groups), dtype=torch.bool
        )
        if groups.shape != (self.G,):
            raise ValueError(f"groups: expected shape ({self.G},), got {tuple(groups.shape)}")
        sel = groups.to(self.torch_device)[:, None, None]
        coords = torch.as_tensor(self.layout.coord_indices, device=self.torch_device)
        with self.on_stream():
            for state in (self.state_0, self.state_1):
                jq = self._state_views["joint_q"](state)
                fresh = jq.clone()
                fresh[..., self._free_coords()] = pose
                fresh[..., coords] = q
                jq.copy_(torch.where(sel, fresh, jq))
                for name in ("joint_qd", "body_qd"):
                    view = self._state_views[name](state)
                    view.masked_fill_(sel, 0.0)
                wp.to_torch(state.body_f).view(self.G, self.K, -1).masked_fill_(sel, 0.0)
            self._warmstart.masked_fill_(sel, 0.0)
            self._wrench.masked_fill_(sel, 0.0)
            self.obs.health.masked_fill_(sel[..., 0], 0)
        worlds = groups.repeat_interleave(self.K).numpy()
        with wp.ScopedDevice(self.device):
            articulations = wp.array(worlds[self.model.articulation_world.numpy()], dtype=bool)
            for state in (self.state_0, self.state_1):
                newton.eval_fk(self.model, state.joint_q, state.joint_qd, state, mask=articulations)
            # flags=0: clear MuJoCo's warm start and applied forces, keep the state just written.
            self.solver.reset(self.state_0, world_mask=wp.array([*worlds, False], dtype=bool), flags=0)

    def displace_object(self, displacement: torch.Tensor) -> None:
        """Move each world's object by a small rigid displacement, shape (G, K, 6): translation
        [m] in the world frame, then rotation vector [rad] in the object's frame about its origin.

        Velocities and the robot stay as they are, so contacts push an object displaced into a
        finger back out within a few substeps. Torch ops only: it runs inside the captured update."""
        if tuple(displacement.shape) != (self.G, self.K, 6):
            raise ValueError(f"displacement: expected shape ({self.G}, {self.K}, 6), got {tuple(displacement.shape)}")
        with self.on_stream():
            free = self._state_views["joint_q"](self.state_0)[..., self._free_coords()]
            rot = quat_multiply(free[..., 3:], quat_exp(displacement[..., 3:]))
            free[..., :3] += displacement[..., :3]
            free[..., 3:] = torch.nn.functional.normalize(rot, dim=-1)

    def _free_coords(self) -> slice:
        start = self._coords - 7  # the object's free joint is the last joint of a world
        return slice(start, start + 7)

    def _check(self, name: str, value, width: int) -> torch.Tensor:
        """Broadcast ``value`` to (G, K, width) on the CPU, with a clear error when it cannot."""
        arr = torch.as_tensor(
            np.asarray(value.cpu() if isinstance(value, torch.Tensor) else value), dtype=torch.float32
        )
        G, K = self.G, self.K
        if arr.shape not in ((G, K, width), (G, width), (width,)):
            raise ValueError(
                f"{name}: expected shape ({G}, {K}, {width}), ({G}, {width}) or ({width},), got {tuple(arr.shape)}"
            )
        if not torch.isfinite(arr).all():
            raise ValueError(f"{name}: {int((~torch.isfinite(arr)).sum())} non-finite values")
        if arr.dim() == 2:
            arr = arr[:, None, :]
        return arr.expand(G, K, width).contiguous()

    # ------------------------------------------------------------------ parameters
    @property
    def mass(self) -> torch.Tensor:
        """Object mass per world, shape (G, K) [kg] (a view: change it with :meth:`set_params`)."""
        return self._mass

    @property
    def friction(self) -> torch.Tensor:
        """Object friction coefficient per world, shape (G, K) (a view: change it with :meth:`set_params`)."""
        return self._friction

    def set_params(self, mass: torch.Tensor | None = None, friction: torch.Tensor | None = None) -> None:
        """Set object mass [kg] (inertia scaled with it) and friction per world, shapes (G, K); a
        ValueError names the parameter and the values outside its range, on every device."""
        if mass is not None:
            mass = self._check_param("mass", mass, self.object.mass_range)
        if friction is not None:
            friction = self._check_param("friction", friction, self.object.friction_range)
        self._write_params(mass, friction)

    def _write_params(self, mass: torch.Tensor | None, friction: torch.Tensor | None) -> None:
        """:meth:`set_params` for values already in range, (G, K) on the device: no host work, so
        it can run inside a captured graph (the tracker's update)."""
        with self.on_stream():
            if mass is not None:
                scale = (mass / self._nominal_mass)[..., None, None]
                self._mass.copy_(mass)
                self._inv_mass.copy_(1.0 / mass)
                self._inertia.copy_(self._nominal_inertia * scale)
                self._inv_inertia.copy_(self._nominal_inv_inertia / scale)
                self._write_solver_inertia()
            if friction is not None:
                self._shape_mu.copy_(friction[..., None].expand_as(self._shape_mu))
        if mass is not None or friction is not None:
            self._notify_shapes()

    def _write_solver_inertia(self) -> None:
        """The solver's copies of the object's inertial constants, from ``mass`` (see _solver_inertia_views)."""
        mj, mj0 = self._mj, self._mj0
        scale = self._mass / self._nominal_mass
        mj["mass"].copy_(self._mass)
        mj["subtree"].copy_(self._mass)
        mj["root_subtree"].copy_(mj0["root_subtree"] + (self._mass - self._nominal_mass))
        mj["inertia"].copy_(mj0["inertia"] * scale[..., None])
        mj["invweight"].copy_(mj0["invweight"] / scale[..., None])
        mj["dof_invweight"].copy_(mj0["dof_invweight"] / scale[..., None])

    def _check_param(self, name: str, value: torch.Tensor, bounds: tuple[float, float]) -> torch.Tensor:
        """``value`` as a (G, K) float32 tensor on the device, after checking it on the host."""
        value = torch.as_tensor(value, dtype=torch.float32)
        if tuple(value.shape) != (self.G, self.K):
            raise ValueError(f"{name}: expected shape ({self.G}, {self.K}), got {tuple(value.shape)}")
        host = value.cpu()
        lo, hi = bounds
        lo32, hi32 = (torch.tensor(b, dtype=torch.float32).item() for b in bounds)  # float32 clipping rounds past
        bad = ~((host >= lo32) & (host <= hi32))  # NaN is outside too
        if bool(bad.any()):
            raise ValueError(f"{name}: {int(bad.sum())} values outside [{lo}, {hi}], e.g. {host[bad][0].item():.4g}")
        return value.to(self.torch_device)

    def _notify_shapes(self) -> None:
        """Push friction to the solver. It also drops the solver's cached contact parameters, which
        a new mass makes stale too; the inertial constants themselves are written directly
        (:meth:`_write_solver_inertia`)."""
        with wp.ScopedDevice(self.device):
            self.solver.notify_model_changed(newton.ModelFlags.SHAPE_PROPERTIES)

    # ------------------------------------------------------------------ resampling
    def resample(self, index: torch.Tensor) -> None:
        """World k of group g becomes a copy of world ``index[g, k]`` of the same group.

        Copies all state (positions, velocities, body poses, the solver's warm start) and the
        physics parameters in place, so a copy evolves bit for bit like its source.
        index: shape (G, K), integer, values in [0, K); a ValueError names what is wrong.
        """
        if tuple(index.shape) != (self.G, self.K):
            raise ValueError(f"index: expected shape ({self.G}, {self.K}), got {tuple(index.shape)}")
        if index.dtype not in (torch.int32, torch.int64):
            raise ValueError(f"index: expected an integer tensor, got {index.dtype}")
        host = index.cpu()
        if bool(((host < 0) | (host >= self.K)).any()):
            raise ValueError(
                f"index: values must lie in [0, {self.K}), got min {int(host.min())} max {int(host.max())}"
            )
        self._resample(index.to(self.torch_device, torch.int64))

    def _resample(self, index: torch.Tensor) -> None:
        """:meth:`resample` for an int64 index on the device already in range: no host work, so
        it can run inside a captured graph (the tracker's update, whose indices never leave the device)."""
        with self.on_stream():
            tensors = [view(self.state_0) for view in self._state_views.values()]
            tensors += [self._warmstart, self._mass[..., None], self._inv_mass[..., None], self._shape_mu]
            tensors += [self._inertia.view(self.G, self.K, 9), self._inv_inertia.view(self.G, self.K, 9)]
            for t in tensors:
                t.copy_(torch.gather(t, 1, index[..., None].expand(-1, -1, t.shape[-1])))
            self._write_solver_inertia()
        self._notify_shapes()
