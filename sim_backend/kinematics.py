"""Forward and inverse kinematics of one robot, off the hot path.

Used to turn a real robot's joint positions into sensor poses, and to plan grasps for tests and
scripted demos. It runs on a private single-world model on the CPU, so it never touches the
population's memory.
"""

from __future__ import annotations

import newton
import numpy as np
import torch
import warp as wp

from .observe import sensor_poses
from .robots import RobotLayout, RobotSpec, add_robot
from .rotations import quat_multiply, quat_rotate

__all__ = ["Kinematics", "SensorFK", "joint_chains"]


class Kinematics:
    """Forward kinematics of the sensor frames, and damped least-squares IK for the fingertips."""

    def __init__(self, spec: RobotSpec):
        builder = newton.ModelBuilder()
        newton.solvers.SolverMuJoCo.register_custom_attributes(builder)
        self.layout: RobotLayout = add_robot(builder, spec)
        self._model = builder.finalize(device="cpu")
        self._state = self._model.state()

    def servos(self) -> dict[str, np.ndarray]:
        """The robot's servo settings as built ("ke", "kd", "effort": its config's, or its file's
        actuators'), each (D,); a joint the robot does not drive has a gain of 0."""
        arrays = {
            "ke": self._model.joint_target_ke,
            "kd": self._model.joint_target_kd,
            "effort": self._model.joint_effort_limit,
        }
        return {name: a.numpy()[self.layout.dof_indices].astype(np.float64) for name, a in arrays.items()}

    def body_poses(self, q: np.ndarray) -> np.ndarray:
        """Poses of all robot bodies for joint positions ``q`` (D,), shape (B, 7) [m, quat xyzw]."""
        q = np.asarray(q, dtype=np.float32)
        if q.shape != (self.layout.dof_count,):
            raise ValueError(f"q: expected shape ({self.layout.dof_count},), got {q.shape}")
        joint_q = self._model.joint_q.numpy()
        joint_q[self.layout.coord_indices] = q
        self._state.joint_q.assign(joint_q)
        newton.eval_fk(self._model, self._state.joint_q, self._state.joint_qd, self._state)
        return self._state.body_q.numpy().astype(np.float64)

    def sensor_poses(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sensor positions (L, 3) [m] and orientations (L, 4) [quat xyzw] for joints ``q`` (D,)."""
        bodies = torch.from_numpy(self.body_poses(q)[self.layout.sensor_bodies])
        off = torch.from_numpy(self.layout.sensor_offsets)
        pos = bodies[:, :3] + quat_rotate(bodies[:, 3:], off[:, :3])
        return pos.numpy(), quat_multiply(bodies[:, 3:], off[:, 3:]).numpy()

    def solve_tips(
        self,
        q_start: np.ndarray,
        targets: np.ndarray,
        *,
        active: np.ndarray,
        iterations: int = 60,
        damping: float = 1e-3,
        weights: np.ndarray | None = None,
    ) -> np.ndarray:
        """Joint positions near ``q_start`` that put the sensor origins at ``targets`` (L, 3) [m].

        Only joints with ``active`` (D,) True move; results stay inside the joint limits. Sensors
        with zero ``weights`` (L,) are ignored.
        """
        lay = self.layout
        q = np.clip(np.asarray(q_start, dtype=np.float64), lay.lower, lay.upper)
        w = np.ones(lay.sensor_count) if weights is None else np.asarray(weights, dtype=np.float64)
        w3 = np.repeat(w, 3)
        idx = np.flatnonzero(active)
        eps = 1e-4
        for _ in range(iterations):
            p0 = self.sensor_poses(q)[0]
            err = (targets - p0).reshape(-1) * w3
            if np.abs(err).max() < 1e-5:
                break
            jac = np.empty((err.size, idx.size))
            for c, j in enumerate(idx):
                dq = q.copy()
                dq[j] += eps
                jac[:, c] = (self.sensor_poses(dq)[0] - p0).reshape(-1) * w3 / eps
            step = jac.T @ np.linalg.solve(jac @ jac.T + damping * np.eye(err.size), err)
            q[idx] = np.clip(q[idx] + step, lay.lower[idx], lay.upper[idx])
        return q


def joint_chains(model: newton.Model, layout: RobotLayout) -> np.ndarray:
    """Which chain (a finger, a wrist) each actuated joint of ``layout`` belongs to, (D,) int from
    0, numbered in joint order: a chain climbs from a joint to its parent joint while that
    parent is actuated and carries no other actuated joint, so it stops below a palm.
    ``model``: any model whose first world holds the robot."""
    start, parent, child = (a.numpy() for a in (model.joint_qd_start, model.joint_parent, model.joint_child))
    joint = np.searchsorted(start, layout.dof_indices, side="right") - 1  # each actuated DOF's joint
    actuated = np.unique(joint)
    moving = {int(child[j]): int(j) for j in actuated}  # body -> the actuated joint that moves it
    below = parent[actuated]
    branches = np.bincount(below[below >= 0], minlength=model.body_count)

    def root(j: int) -> int:
        while (up := moving.get(int(parent[j]))) is not None and branches[parent[j]] == 1:
            j = up
        return j

    roots = [root(int(j)) for j in joint]
    return np.unique(roots, return_inverse=True)[1].astype(np.int64)


class SensorFK:
    """Sensor poses of G robots from their joint positions, on the device, as torch tensors.

    The tracker needs the real robot's sensor poses every frame; robots send only joints, so this
    runs forward kinematics of a robot-only model of G worlds with the population's own kernel.
    """

    def __init__(self, spec: RobotSpec, groups: int, device: wp.context.Device):
        world = newton.ModelBuilder()
        newton.solvers.SolverMuJoCo.register_custom_attributes(world)
        self.layout = lay = add_robot(world, spec)
        builder = newton.ModelBuilder()
        builder.replicate(world, groups)
        self.device = device
        with wp.ScopedDevice(device):
            self._model = builder.finalize(device=device)
            self._state = self._model.state()
            L = lay.sensor_count
            self._pos = wp.zeros((groups, L), dtype=wp.vec3)
            self._rot = wp.zeros((groups, L), dtype=wp.quat)
            self._scratch = [wp.zeros((groups, L), dtype=t) for t in (wp.vec3, wp.vec3, wp.vec3, float)]
            offsets = [wp.transform(wp.vec3(*o[:3]), wp.quat(*o[3:])) for o in lay.sensor_offsets]
            self._offsets = wp.array(offsets, dtype=wp.transform)
            self._bodies = wp.array(lay.sensor_bodies.astype(np.int32), dtype=wp.int32)
        self._groups, self._per_world = groups, world.body_count
        torch_q = wp.to_torch(self._state.joint_q).view(groups, world.joint_coord_count)
        self._q = torch_q[:, lay.coord_indices[0] : lay.coord_indices[0] + lay.dof_count]
        if not np.array_equal(lay.coord_indices, np.arange(lay.coord_indices[0], lay.coord_indices[0] + lay.dof_count)):
            raise ValueError(f"robot '{lay.name}': actuated joints must be contiguous coordinates for SensorFK")
        self.pos = wp.to_torch(self._pos).view(groups, L, 3)
        """Sensor positions after :meth:`update`, (G, L, 3) [m]."""
        self.rot = wp.to_torch(self._rot).view(groups, L, 4)
        """Sensor orientations after :meth:`update`, (G, L, 4) quaternion (x, y, z, w)."""

    def update(self, q) -> None:
        """Forward kinematics of joint positions ``q`` (G, D), a torch tensor on the device."""
        self._q.copy_(q)
        with wp.ScopedDevice(self.device):
            newton.eval_fk(self._model, self._state.joint_q, self._state.joint_qd, self._state)
            wp.launch(
                sensor_poses,
                dim=(self._groups, self.layout.sensor_count),
                inputs=[self._state.body_q, self._per_world, self._bodies, self._offsets],
                outputs=[self._pos, self._rot, *self._scratch],
            )
