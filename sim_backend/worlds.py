"""The worlds' frame record: everything one control frame of the G x K worlds reads and writes.

Static model, changing state and inputs apart, as Newton's Model/State/Control and MuJoCo-Warp's
``step(m, d)`` keep them: :class:`Dims` and :class:`FrameIndex` are fixed at build, the states,
control and buffers change every frame. The frame's stages (:func:`.step.simulate`,
:func:`.step.observe_frame`, :func:`.separate.separate_objects`) take this record and nothing else,
so none of them needs the :class:`~.population.Population` that owns it.
"""

from __future__ import annotations

from dataclasses import dataclass

import newton
import numpy as np
import warp as wp

from .build import BuiltModel, Physics
from .config import PopulationConfig
from .observe import Buffers, allocate_buffers
from .robot_specs import RobotLayout
from .zones import zone_arrays

__all__ = ["Dims", "FrameIndex", "Worlds", "allocate_worlds", "frame_index"]


@dataclass(frozen=True)
class Dims:
    """The sizes of the population and of one world."""

    G: int
    """Groups (tracking sessions)."""
    K: int
    """Worlds per group."""
    D: int
    """The robot's actuated joints."""
    L: int
    """The robot's force sensors."""
    Z: int
    """The robot's touch zones."""
    bodies: int
    """Bodies per world."""
    coords: int
    """Joint coordinates per world (the object's free joint last: 7)."""
    dofs: int
    """Joint DOFs per world."""
    object_body: int
    """The object's body index within a world."""

    @property
    def W(self) -> int:
        """Worlds in all, G * K."""
        return self.G * self.K

    @property
    def free_coords(self) -> slice:
        """Where the object's free joint lies among a world's joint coordinates."""
        start = self.coords - 7  # the object's free joint is the last joint of a world
        return slice(start, start + 7)


@dataclass(frozen=True)
class FrameIndex:
    """The index arrays the frame's kernels read, on the population's device."""

    coord_index: wp.array
    """(D,) int32: each actuated joint's coordinate within a world."""
    sensor_body: wp.array
    """(L,) int32: each force sensor's body within a world."""
    sensor_offset: wp.array
    """(L,) transform: each sensor's frame in its body's [m, quat xyzw]."""
    sensor_row: wp.array
    """(bodies in all,) int32: the sensor row (w * L + l) a body carries, else -1."""
    object_world: wp.array
    """(bodies in all,) int32: w when the body is world w's object, else -1."""
    zone_first: wp.array
    """(bodies per world + 1,) int32: the touch zones on local body b are ``zone_first[b]`` .. ``[b + 1]``."""
    zone_index: wp.array
    """(Z,) int32: each zone's place in the record, in zone_first's order."""
    zone_center: wp.array
    """(Z,) vec3: each zone's box centre in its link's frame [m]."""
    zone_half: wp.array
    """(Z,) vec3: each zone's box half extents [m]."""


def frame_index(layout: RobotLayout, dims: Dims, body_count: int) -> FrameIndex:
    """The frame's index arrays for ``layout`` in a model of ``body_count`` bodies (current device)."""
    W, nb = dims.W, dims.bodies
    sensor_row = np.full(body_count, -1, np.int32)
    object_world = np.full(body_count, -1, np.int32)
    worlds = np.arange(W)
    for l, b in enumerate(layout.sensor_bodies):
        sensor_row[worlds * nb + b] = worlds * dims.L + l
    object_world[worlds * nb + dims.object_body] = worlds
    offsets = [wp.transform(wp.vec3(*o[:3]), wp.quat(*o[3:])) for o in layout.sensor_offsets]
    return FrameIndex(
        coord_index=wp.array(layout.coord_indices.astype(np.int32), dtype=wp.int32),
        sensor_body=wp.array(layout.sensor_bodies.astype(np.int32), dtype=wp.int32),
        sensor_offset=wp.array(offsets, dtype=wp.transform),
        sensor_row=wp.array(sensor_row, dtype=wp.int32),
        object_world=wp.array(object_world, dtype=wp.int32),
        **zone_arrays(layout, nb),
    )


@dataclass
class Worlds:
    """What one control frame of every world reads and writes: the model and its physics (static),
    the two state buffers and the control (changing), the observation buffers (outputs)."""

    config: PopulationConfig
    dims: Dims
    layout: RobotLayout
    """The robot's joints, sensors, zones and limits in one world."""
    model: newton.Model
    solver: newton.solvers.SolverMuJoCo
    pipeline: newton.CollisionPipeline
    contacts: newton.Contacts
    observables: object
    """The solver's contact forces (read by the observation kernels) and its overflow bitmask."""
    state_0: newton.State
    """The state a frame starts from and ends in (substeps alternate with ``state_1``)."""
    state_1: newton.State
    control: newton.Control
    buf: Buffers
    """The observation kernels' arrays, leading axis W (:mod:`.observe`)."""
    goal: wp.array
    """(W, D): the robot's command for this frame, when targets are ramped [rad or m]."""
    last_goal: wp.array
    """(W, D): the last frame's command, where this frame's ramp starts [rad or m]."""
    index: FrameIndex


def allocate_worlds(config: PopulationConfig, dims: Dims, built: BuiltModel, physics: Physics) -> Worlds:
    """The frame's record for ``built`` stepped by ``physics``, its arrays made on the current device."""
    model = built.model
    return Worlds(
        config=config,
        dims=dims,
        layout=built.layout,
        model=model,
        solver=physics.solver,
        pipeline=physics.pipeline,
        contacts=physics.contacts,
        observables=physics.observables,
        state_0=model.state(),
        state_1=model.state(),
        control=model.control(),
        buf=allocate_buffers(dims.W, dims.D, dims.L, dims.Z),
        goal=wp.zeros((dims.W, dims.D), dtype=float),
        last_goal=wp.zeros((dims.W, dims.D), dtype=float),
        index=frame_index(built.layout, dims, model.body_count),
    )
