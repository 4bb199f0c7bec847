"""The population: G groups x K worlds of hand + object in one Newton model, stepped as one graph.

World ``w = g * K + k`` is world ``k`` of group ``g``. Every per-world quantity is exposed as a
torch view of the Warp array it lives in (``wp.to_torch``, no copy), shaped (G, K, ...), so the
tracker's cost and resampling are torch ops on the simulation's own memory.

One control frame (all substeps, the collision pipeline, the observation kernels) is captured
once as a graph and replayed by :meth:`Population.step`, on CUDA and on Warp's CPU device alike.
"""

from __future__ import annotations

import contextlib
from contextlib import AbstractContextManager

import newton
import numpy as np
import torch
import warp as wp

from . import observe
from .build import DROPPED, build_model, contact_capacity, make_physics, resolve_physics, say_timestep
from .config import PopulationConfig, resolve_device
from .objects import ObjectSpec
from .params import ObjectParams
from .robots import SERVO_ARRAYS, RobotLayout, RobotSpec
from .rotations import quat_exp, quat_multiply
from .separate import separate_objects
from .step import no_collection, simulate
from .worlds import Dims, allocate_worlds

__all__ = ["Population"]


class Population:
    """G x K worlds of one robot and one object type, stepped in lock-step.

    Typical frame: :meth:`set_targets` with the robot's controls, then :meth:`step`; read
    :attr:`obs`. Between frames: :meth:`resample`, :meth:`set_params`, :meth:`set_wrench`.
    """

    def __init__(
        self,
        robot: RobotSpec,
        obj: ObjectSpec,
        config: PopulationConfig | None = None,
        turn: AbstractContextManager | None = None,
    ):
        """``turn``: entered around each stage of the build that uses the device (upload, solver,
        buffers, capture), so that a population can be built on one thread while another steps
        the others between those stages; Warp's current stream is per device, not per thread, so
        the stages must not interleave with another thread's device work."""
        turn = turn or contextlib.nullcontext()
        self.config = cfg = config or PopulationConfig()
        self.device = resolve_device(cfg.device)
        self.robot_spec = robot
        self.object = obj
        self.G, self.K, self.W = cfg.groups, cfg.worlds, cfg.world_count
        torch_device = wp.device_to_torch(self.device)
        self.torch_device = torch.device(torch_device)
        self._torch_stream = wp.stream_to_torch(self.device.stream) if self.device.is_cuda else None

        self.built = built = build_model(robot, obj, cfg, self.device, turn)
        """The replicated model and what one world of it holds (static)."""
        self.config = cfg = resolve_physics(robot, contact_capacity(built, cfg), built.layout)
        say_timestep(robot.name, built.layout, cfg)
        self.model = built.model
        self.layout: RobotLayout = built.layout
        self.object_body, self.bodies, self.coords, self._dofs = (
            built.object_body, built.bodies, built.coords, built.dofs
        )  # fmt: skip
        """Per world: the object's body index, and its bodies, joint coordinates and DOFs in all."""
        self.D, self.L, self.Z = self.layout.dof_count, self.layout.sensor_count, self.layout.zone_count
        self.dims = Dims(self.G, self.K, self.D, self.L, self.Z, self.bodies, self.coords, self._dofs, self.object_body)
        with turn:
            physics = make_physics(self.model, cfg, self.device)
        self.solver, self.pipeline, self.contacts = physics.solver, physics.pipeline, physics.contacts
        with turn, wp.ScopedDevice(self.device):
            self.data = allocate_worlds(cfg, self.dims, built, physics)
            """What the frame's stages read and write (:class:`.Worlds`)."""
            self.state_0, self.state_1 = self.data.state_0, self.data.state_1
            self.params = ObjectParams(built, physics, self.G, self.K, self.torch_device)
            """The object's mass and friction per world and the solver's constants they set."""
            self._views()
            self.obs = observe.observation_views(self.data.buf, self.G, self.K)
            self.reset_state()
            mass, friction = (torch.full((self.G, self.K), v) for v in (obj.mass, obj.friction))
            self.set_params(mass=mass, friction=friction)
            self.set_targets(np.broadcast_to(self.layout.default_q, (self.G, self.D)))
        self._graph = None
        if cfg.use_graph:
            self._capture(turn)

    # ------------------------------------------------------------------ build
    def _views(self) -> None:
        """Torch views (no copies) of the per-world simulation arrays, leading axes (G, K)."""
        G, K, nb = self.G, self.K, self.bodies
        t = wp.to_torch
        self.state_views = {
            "joint_q": lambda s: t(s.joint_q).view(G, K, self.coords),
            "joint_qd": lambda s: t(s.joint_qd).view(G, K, self._dofs),
            "body_q": lambda s: t(s.body_q).view(G, K, nb * 7),
            "body_qd": lambda s: t(s.body_qd).view(G, K, nb * 6),
        }
        self._warmstart = t(self.solver.mjw_data.qacc_warmstart).view(G, K, -1)
        # Position targets live in joint-coordinate layout, like joint_q.
        dof = self.layout.coord_indices
        d = self.data
        targets = t(d.control.joint_target_q).view(G, K, self.coords)
        contiguous = np.array_equal(dof, np.arange(dof[0], dof[0] + len(dof)))
        self._target_view = targets[..., dof[0] : dof[0] + len(dof)] if contiguous else None
        self._targets_all = targets
        self._target_index = torch.as_tensor(dof, device=self.torch_device)
        self._dof_index = torch.as_tensor(self.layout.dof_indices, device=self.torch_device)
        self._servo_views: dict[str, torch.Tensor] = {}
        self._goal_view = t(d.goal).view(G, K, self.D)
        self._last_goal_view = t(d.last_goal).view(G, K, self.D)
        self._target_stage = torch.zeros((G, self.D), dtype=torch.float32, device=self.torch_device)
        self._lower = torch.as_tensor(self.layout.lower, dtype=torch.float32, device=self.torch_device)
        self._upper = torch.as_tensor(self.layout.upper, dtype=torch.float32, device=self.torch_device)
        self._wrench = t(d.buf.wrench).view(G, K, 6)
        self.overflow = t(d.observables.overflow).view(G, K)
        """What each world's last substep overflowed, (G, K) int32 bitmask
        (newton.solvers.SolverMuJoCo.OverflowBits): 0 when nothing did; :meth:`dropped` reads it."""

    def _capture(self, turn: AbstractContextManager) -> None:
        # Compile every kernel once outside capture, then record; the eager frame is undone.
        with turn, wp.ScopedDevice(self.device):
            saved = self.snapshot()
            simulate(self.data)
            self.restore(saved)
        with turn, wp.ScopedDevice(self.device), no_collection(), wp.ScopedCapture(device=self.device) as capture:
            simulate(self.data)
        self._graph = capture.graph

    def state_tensors(self) -> list[torch.Tensor]:
        """Every tensor that carries a world's dynamic state from one frame to the next."""
        views = [view(s) for s in (self.state_0, self.state_1) for view in self.state_views.values()]
        return [*views, self._warmstart, self._last_goal_view]

    def snapshot(self) -> list[torch.Tensor]:
        """Copies of :meth:`state_tensors`, to :meth:`restore` later."""
        with self.on_stream():
            return [t.clone() for t in self.state_tensors()]

    def restore(self, saved: list[torch.Tensor]) -> None:
        """Put back a :meth:`snapshot`."""
        with self.on_stream():
            for t, s in zip(self.state_tensors(), saved, strict=True):
                t.copy_(s)

    def step(self) -> None:
        """Advance every world by one control frame (one graph replay).

        Called while an enclosing graph is being captured on the device (the tracker's frame), it
        launches the frame's kernels into that capture instead."""
        with wp.ScopedDevice(self.device):
            if self._graph is not None and not self.device.is_capturing:
                wp.capture_launch(self._graph)
            else:
                simulate(self.data)

    def dropped(self) -> torch.Tensor:
        """Which worlds' last substep left contacts or constraint rows out for want of room, (G, K) bool."""
        return (self.overflow & DROPPED) != 0

    def step_eager(self) -> None:
        """The same frame launched kernel by kernel (for checking the graph)."""
        with wp.ScopedDevice(self.device):
            simulate(self.data)

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
        self.write_targets(torch.from_numpy(arr))

    def write_targets(self, targets: torch.Tensor) -> None:
        """:meth:`set_targets` for targets already checked, (G, D): no host work, so it can run
        inside a captured graph (the tracker's frame)."""
        with self.on_stream():
            self._target_stage.copy_(targets, non_blocking=True)
            torch.clamp(self._target_stage, self._lower, self._upper, out=self._target_stage)
            if self.config.ramp_targets:
                self._goal_view.copy_(self._target_stage[:, None, :].expand(self.G, self.K, self.D))
            elif self._target_view is not None:
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
                jq = self.state_views["joint_q"](state)
                fresh = jq.clone()
                fresh[..., self.free_coords] = pose
                fresh[..., coords] = q
                jq.copy_(torch.where(sel, fresh, jq))
                for name in ("joint_qd", "body_qd"):
                    view = self.state_views[name](state)
                    view.masked_fill_(sel, 0.0)
                wp.to_torch(state.body_f).view(self.G, self.K, -1).masked_fill_(sel, 0.0)
            self._warmstart.masked_fill_(sel, 0.0)
            self._wrench.masked_fill_(sel, 0.0)
            # A ramp starts where the robot stands.
            self._last_goal_view.copy_(torch.where(sel, q, self._last_goal_view))
            self.obs.health.masked_fill_(sel[..., 0], 0)
        worlds = groups.repeat_interleave(self.K).numpy()
        with wp.ScopedDevice(self.device):
            articulations = wp.array(worlds[self.model.articulation_world.numpy()], dtype=bool)
            for state in (self.state_0, self.state_1):
                newton.eval_fk(self.model, state.joint_q, state.joint_qd, state, mask=articulations)
            # flags=0: clear MuJoCo's warm start and applied forces, keep the state just written.
            self.solver.reset(self.state_0, world_mask=wp.array([*worlds, False], dtype=bool), flags=0)

    def separate_object(self, worlds: torch.Tensor | np.ndarray, passes: int = 6) -> None:
        """Move the object of each world in ``worlds`` (G, K) bool out of whatever it overlaps
        (the hand, the table) by a translation along the contacts' normals, as far as the
        overlaps go; the robot, the rotation and the velocities stay. A drawn pose a few
        millimetres inside a palm would otherwise be pushed out by the solver at a speed that
        throws a light object off the hand. ``passes`` rounds of collision detection: a corner
        pushed out of the palm may meet a finger."""
        with self.on_stream():
            separate_objects(self.data, worlds, passes)

    def displace_object(self, displacement: torch.Tensor) -> None:
        """Move each world's object by a small rigid displacement, shape (G, K, 6): translation
        [m] in the world frame, then rotation vector [rad] in the object's frame about its origin.

        Velocities and the robot stay as they are, so contacts push an object displaced into a
        finger back out within a few substeps. Torch ops only: it runs inside the captured update."""
        if tuple(displacement.shape) != (self.G, self.K, 6):
            raise ValueError(f"displacement: expected shape ({self.G}, {self.K}, 6), got {tuple(displacement.shape)}")
        with self.on_stream():
            free = self.state_views["joint_q"](self.state_0)[..., self.free_coords]
            rot = torch.nn.functional.normalize(quat_multiply(free[..., 3:], quat_exp(displacement[..., 3:])), dim=-1)
            free[..., :3] += displacement[..., :3]
            # A world not displaced keeps its state to the bit: renormalising would move it by rounding.
            free[..., 3:] = torch.where(displacement[..., 3:].ne(0).any(-1, keepdim=True), rot, free[..., 3:])

    @property
    def object_coords(self) -> torch.Tensor:
        """Each world's object pose in its state, (G, K, 7): position [m], quaternion (x, y, z, w);
        a writable view (the observed pose, :attr:`obs` ``.object_pose``, follows at the next step)."""
        return self.state_views["joint_q"](self.state_0)[..., self.free_coords]

    @property
    def joint_qd(self) -> torch.Tensor:
        """Each world's joint velocities in its state, (G, K, DOFs per world) [rad/s or m/s]; a writable view."""
        return self.state_views["joint_qd"](self.state_0)

    @property
    def free_coords(self) -> slice:
        """Where the object's free joint lies among a world's joint coordinates."""
        return self.dims.free_coords

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
        return self.params.mass

    @property
    def friction(self) -> torch.Tensor:
        """Object friction coefficient per world, shape (G, K) (a view: change it with :meth:`set_params`)."""
        return self.params.friction

    def set_params(self, mass: torch.Tensor | None = None, friction: torch.Tensor | None = None) -> None:
        """Set object mass [kg] (inertia scaled with it) and friction per world, shapes (G, K); a
        ValueError names the parameter and the values outside its range, on every device."""
        if mass is not None:
            mass = self._check_param("mass", mass, self.object.mass_range)
        if friction is not None:
            friction = self._check_param("friction", friction, self.object.friction_range)
        self.write_params(mass, friction)

    def write_params(
        self,
        mass: torch.Tensor | None,
        friction: torch.Tensor | None,
        timeconst: torch.Tensor | None = None,
        impratio: torch.Tensor | None = None,
    ) -> None:
        """:meth:`set_params` for values already in range, (G, K) on the device: no host work, so
        it can run inside a captured graph (the tracker's update). ``timeconst`` [s] and
        ``impratio``: the object's contacts (:class:`ObjectParams`)."""
        with self.on_stream():
            self.params.write(mass, friction)
            self.params.write_contacts(timeconst, impratio)
        if any(x is not None for x in (mass, friction, timeconst, impratio)):
            self.params.notify(self.device)

    def servos(self, name: str) -> torch.Tensor:
        """The robot's servo setting ``name`` (:data:`SERVO_ARRAYS`: "ke" gain [N m/rad or N/m],
        "kd" damping [N m s/rad or N s/m], "effort" limit [N m or N], the joint's own "damping",
        "armature", "friction") in every world, (G, K, D): a copy."""
        return self._servo_array(name)[..., self._dof_index]

    def set_servos(self, **settings: torch.Tensor | np.ndarray) -> None:
        """Give each world its own servos: settings as in :meth:`servos`, each (G, K, D) or
        broadcastable, finite and >= 0 (a ValueError names the setting)."""
        checked = {}
        for name, value in settings.items():
            if name not in SERVO_ARRAYS:
                raise ValueError(f"servos: unknown setting '{name}' (known: {sorted(SERVO_ARRAYS)})")
            value = torch.as_tensor(value, dtype=torch.float32, device=self.torch_device)
            if not bool(torch.isfinite(value).all() and (value >= 0).all()):
                raise ValueError(f"servos {name}: expected finite values >= 0, got min {value.min().item():.4g}")
            checked[name] = value.expand(self.G, self.K, self.D)
        self.write_servos(checked)

    def write_servos(self, settings: dict[str, torch.Tensor]) -> None:
        """:meth:`set_servos` for values already checked, (G, K, D) on the device: without an
        armature (inertia, which the solver republishes on the host) no host work, so it can run
        inside a captured graph (the tracker's servo exploration)."""
        flags = newton.ModelFlags
        with self.on_stream():
            for name, value in settings.items():
                self._servo_array(name).index_copy_(2, self._dof_index, value)
            self.solver.notify_model_changed(
                flags.JOINT_DOF_PROPERTIES if "armature" in settings else flags.JOINT_DOF_FORCE_PROPERTIES
            )

    def _servo_array(self, name: str) -> torch.Tensor:  # the whole per-DOF array, (G, K, DOFs): a view
        if name not in self._servo_views:
            array = wp.to_torch(getattr(self.model, SERVO_ARRAYS[name]))
            self._servo_views[name] = array.view(self.G, self.K, self._dofs)
        return self._servo_views[name]

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
        low, high = int(index.min()), int(index.max())
        if low < 0 or high >= self.K:
            raise ValueError(f"index: values must lie in [0, {self.K}), got min {low} max {high}")
        self.copy_worlds(index.to(self.torch_device, torch.int64))

    def copy_worlds(self, index: torch.Tensor, params_index: torch.Tensor | None = None) -> None:
        """:meth:`resample` for an int64 index on the device already in range: no host work, so
        it can run inside a captured graph (the tracker's update, whose indices never leave the device).
        ``params_index`` (G, K): where the physics parameters come from instead, each world then
        simulating its own state (or its ``index`` source's) with another world's parameters."""
        params_index = index if params_index is None else params_index
        with self.on_stream():
            state = [view(self.state_0) for view in self.state_views.values()] + [self._warmstart]
            for tensors, source in ((state, index), (self.params.tensors, params_index)):
                for t in tensors:
                    t.copy_(torch.gather(t, 1, source[..., None].expand(-1, -1, t.shape[-1])))
            self.params.write_solver_constants()
        self.params.notify(self.device)
