"""One control frame of every world: the perturbation wrench, the substeps (targets ramped
between frames, collision, the solver), and the observation kernels. Captured once as a graph by
the population and replayed per frame."""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from . import health, observe
from .build import contact_points
from .zones import zone_arrays

if TYPE_CHECKING:
    from .population import Population

__all__ = ["frame_arrays", "no_collection", "observe_frame", "simulate"]


@contextlib.contextmanager
def no_collection() -> Iterator[None]:
    """No cycle collection (on any thread) while a CUDA graph is captured: a dropped population's
    graphs live in a reference cycle, and freeing a graph during another's capture invalidates it."""
    gc.collect()
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if collecting:
            gc.enable()


@wp.kernel(enable_backward=False)
def ramp_targets(
    goal: wp.array2d[float],
    last: wp.array2d[float],
    fraction: float,
    coords_per_world: int,
    coord_index: wp.array[wp.int32],
    joint_target_q: wp.array[float],
):
    """The substep's target: ``fraction`` of the way from last frame's target to this one's. Launch dim (W, D)."""
    w, d = wp.tid()
    joint_target_q[w * coords_per_world + coord_index[d]] = last[w, d] + fraction * (goal[w, d] - last[w, d])


@wp.kernel(enable_backward=False)
def apply_wrench(
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


def simulate(pop: Population) -> None:
    """One control frame of ``pop``: wrench, substeps, observation."""
    cfg, b, s = pop.config, pop.buf, pop.static
    wp.launch(
        apply_wrench,
        dim=pop.W,
        inputs=[b.wrench, pop.bodies, pop.object_body],
        outputs=[pop.state_0.body_f, pop.state_1.body_f],
    )
    dt = cfg.frame_dt / cfg.substeps
    for i in range(cfg.substeps):
        s_in, s_out = (pop.state_0, pop.state_1) if i % 2 == 0 else (pop.state_1, pop.state_0)
        if cfg.ramp_targets:
            wp.launch(ramp_targets, dim=(pop.W, pop.D),
                      inputs=[pop.goal, pop.last_goal, (i + 1) / cfg.substeps, pop.coords, s["coord_index"]],
                      outputs=[pop.control.joint_target_q])  # fmt: skip
        pop.pipeline.collide(s_in, pop.contacts)
        # Only the last substep's contact forces are observed: earlier ones would be overwritten.
        observables = pop.observables if i == cfg.substeps - 1 else None
        pop.solver.step(s_in, s_out, pop.control, pop.contacts, dt, observables=observables)
    b.wrench.zero_()  # a perturbation lasts one frame
    if cfg.ramp_targets:
        wp.copy(pop.last_goal, pop.goal)
    observe_frame(pop)


def observe_frame(pop: Population) -> None:
    """What every world's robot senses after the frame's last substep (:mod:`.observe`)."""
    b, s = pop.buf, pop.static
    cfg = pop.config
    st = pop.state_0
    wp.launch(observe.gather_joints, dim=(pop.W, pop.D), inputs=[st.joint_q, pop.coords, s["coord_index"]],
              outputs=[b.q])  # fmt: skip
    wp.launch(
        observe.sensor_poses,
        dim=(pop.W, pop.L),
        inputs=[st.body_q, pop.bodies, s["sensor_body"], s["sensor_offset"]],
        outputs=[b.sensor_pos, b.sensor_rot, b.force_acc, b.slip_acc, b.spin_acc, b.weight_acc],
    )
    c = pop.contacts
    if pop.Z:
        b.touch.zero_()  # the sensors' sums are cleared by sensor_poses, the zones' here
    b.hand_contacts.zero_()
    b.rest_contacts.zero_()
    wp.launch(
        observe.accumulate_contacts,
        dim=c.rigid_contact_max,
        inputs=[
            *contact_points(c),
            c.rigid_contact_point1,
            c.rigid_contact_offset0,
            c.rigid_contact_offset1,
            c.rigid_contact_normal,
            pop.observables.contact_f,
            pop.model.shape_body,
            st.body_q,
            st.body_qd,
            pop.model.body_com,
            s["sensor_row"],
            s["object_world"],
            pop.L,
            pop.bodies,
            s["zone_first"],
            s["zone_index"],
            s["zone_center"],
            s["zone_half"],
        ],
        outputs=[b.force_acc, b.slip_acc, b.spin_acc, b.weight_acc, b.touch, b.hand_contacts, b.rest_contacts],
    )
    observe.launch_finish(b, cfg.slip_speed, cfg.spin_speed)
    wp.launch(
        health.object_health,
        dim=pop.W,
        inputs=[
            st.body_q,
            st.body_qd,
            st.joint_q,
            pop.bodies,
            pop.coords,
            pop.object_body,
            b.sensor_pos,
            pop.L,
            cfg.floor_z,
            cfg.lost_distance,
            cfg.lost_speed,
            b.hand_contacts,
            b.rest_contacts,
            int(pop.layout.carries_on_palm),
        ],
        outputs=[b.object_pose, b.health],
    )


def frame_arrays(pop: Population) -> dict[str, wp.array]:
    """The index arrays the frame's kernels read: each actuated joint's coordinate, each sensor's
    body and offset, which bodies carry sensors and objects, and the touch zones."""
    lay, W, nb = pop.layout, pop.W, pop.bodies
    sensor_row = np.full(pop.model.body_count, -1, np.int32)
    object_world = np.full(pop.model.body_count, -1, np.int32)
    worlds = np.arange(W)
    for l, b in enumerate(lay.sensor_bodies):
        sensor_row[worlds * nb + b] = worlds * pop.L + l
    object_world[worlds * nb + pop.object_body] = worlds
    offsets = [wp.transform(wp.vec3(*o[:3]), wp.quat(*o[3:])) for o in lay.sensor_offsets]
    return {
        "coord_index": wp.array(lay.coord_indices.astype(np.int32), dtype=wp.int32),
        "sensor_body": wp.array(lay.sensor_bodies.astype(np.int32), dtype=wp.int32),
        "sensor_offset": wp.array(offsets, dtype=wp.transform),
        "sensor_row": wp.array(sensor_row, dtype=wp.int32),
        "object_world": wp.array(object_world, dtype=wp.int32),
        **zone_arrays(pop),
    }
