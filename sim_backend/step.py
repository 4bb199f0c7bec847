"""One control frame of every world: the perturbation wrench, the substeps (targets ramped
between frames, collision, the solver), and the observation kernels. Captured once as a graph by
the population and replayed per frame."""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator

import warp as wp

from . import health, observe
from .build import contact_points
from .duplicates import drop_duplicate_contacts
from .worlds import Worlds

__all__ = ["no_collection", "observe_frame", "simulate"]


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


def simulate(d: Worlds) -> None:
    """One control frame of the worlds ``d``: wrench, substeps, observation."""
    cfg, n, b, ix = d.config, d.dims, d.buf, d.index
    wp.launch(
        apply_wrench,
        dim=n.W,
        inputs=[b.wrench, n.bodies, n.object_body],
        outputs=[d.state_0.body_f, d.state_1.body_f],
    )
    dt = cfg.frame_dt / cfg.substeps
    for i in range(cfg.substeps):
        s_in, s_out = (d.state_0, d.state_1) if i % 2 == 0 else (d.state_1, d.state_0)
        if cfg.ramp_targets:
            wp.launch(ramp_targets, dim=(n.W, n.D),
                      inputs=[d.goal, d.last_goal, (i + 1) / cfg.substeps, n.coords, ix.coord_index],
                      outputs=[d.control.joint_target_q])  # fmt: skip
        if cfg.collision == "newton":
            d.pipeline.collide(s_in, d.contacts)
            if cfg.drop_duplicate_contacts:
                drop_duplicate_contacts(d.contacts)
        # Only the last substep's contacts and forces are observed: earlier ones would be
        # overwritten. Under MuJoCo's collision that export also writes the contacts themselves.
        observables = d.observables if i == cfg.substeps - 1 else None
        d.solver.step(s_in, s_out, d.control, d.contacts, dt, observables=observables)
    b.wrench.zero_()  # a perturbation lasts one frame
    if cfg.ramp_targets:
        wp.copy(d.last_goal, d.goal)
    observe_frame(d)


def observe_frame(d: Worlds) -> None:
    """What every world's robot senses after the frame's last substep (:mod:`.observe`)."""
    cfg, n, b, ix = d.config, d.dims, d.buf, d.index
    st = d.state_0
    wp.launch(observe.gather_joints, dim=(n.W, n.D), inputs=[st.joint_q, n.coords, ix.coord_index],
              outputs=[b.q])  # fmt: skip
    wp.launch(
        observe.sensor_poses,
        dim=(n.W, n.L),
        inputs=[st.body_q, n.bodies, ix.sensor_body, ix.sensor_offset],
        outputs=[b.sensor_pos, b.sensor_rot, b.force_acc, b.slip_acc, b.spin_acc, b.weight_acc],
    )
    c = d.contacts
    if n.Z:
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
            d.observables.contact_f,
            d.model.shape_body,
            st.body_q,
            st.body_qd,
            d.model.body_com,
            ix.sensor_row,
            ix.object_world,
            n.L,
            n.bodies,
            ix.zone_first,
            ix.zone_index,
            ix.zone_center,
            ix.zone_half,
        ],
        outputs=[b.force_acc, b.slip_acc, b.spin_acc, b.weight_acc, b.touch, b.hand_contacts, b.rest_contacts],
    )
    observe.launch_finish(b, cfg.slip_speed, cfg.spin_speed)
    wp.launch(
        health.object_health,
        dim=n.W,
        inputs=[
            st.body_q,
            st.body_qd,
            st.joint_q,
            n.bodies,
            n.coords,
            n.object_body,
            b.sensor_pos,
            n.L,
            cfg.floor_z,
            cfg.lost_distance,
            cfg.lost_speed,
            b.hand_contacts,
            b.rest_contacts,
            int(d.layout.carries_on_palm),
        ],
        outputs=[b.object_pose, b.health],
    )
