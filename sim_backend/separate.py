"""Separation: push hypotheses whose object overlaps the hand or the table out of it.

A pose drawn around a noisy estimate of an object lying on a palm or a table often puts the object
a few millimetres inside it. Left there, the solver pushes it out within a substep or two, and on
a light object pressed between a palm and a finger's links that push launches it at over 1 m/s, off
the hand: a hypothesis lost before its first frame was scored. So a freshly drawn object is first
moved out along the contacts' normals, translation only, the way the solver would push it but
without the speed.

No library does this for a batch of Newton worlds: the collision pipeline finds the overlaps, and
one kernel turns each world's into a push.
"""

from __future__ import annotations

import newton
import numpy as np
import torch
import warp as wp

from .build import contact_points
from .worlds import Worlds

__all__ = ["object_push", "separate_objects"]


@wp.kernel(enable_backward=False)
def object_push(
    contact_count: wp.array[wp.int32],
    shape0: wp.array[wp.int32],
    shape1: wp.array[wp.int32],
    point0: wp.array[wp.vec3],
    point1: wp.array[wp.vec3],
    normal: wp.array[wp.vec3],
    margin0: wp.array[wp.float32],
    margin1: wp.array[wp.float32],
    shape_body: wp.array[wp.int32],
    body_q: wp.array[wp.transform],
    object_world: wp.array[wp.int32],
    push_sum: wp.array[wp.vec3],
    depth_sum: wp.array[wp.float32],
):
    """Sum, per world, the pushes that would end each overlap of its object with anything else
    (the overlap's depth [m] along the contact normal, away from the other shape), each weighted
    by its depth, and the depths: their ratio is the world's push, led by its deepest overlaps, so
    that a corner deep in the palm is not outvoted by the face's shallow ones. ``object_world[b]``
    is w when body b is world w's object, else -1. Launch dim: contact capacity."""
    c = wp.tid()
    if c >= contact_count[0]:
        return
    b0 = shape_body[shape0[c]]
    b1 = shape_body[shape1[c]]
    w0 = wp.int32(-1)
    w1 = wp.int32(-1)
    p0 = point0[c]  # a static shape's (body -1) contact point is in the world frame already
    p1 = point1[c]
    if b0 >= 0:
        w0 = object_world[b0]
        p0 = wp.transform_point(body_q[b0], p0)
    if b1 >= 0:
        w1 = object_world[b1]
        p1 = wp.transform_point(body_q[b1], p1)
    if (w0 < 0) == (w1 < 0):
        return  # not the object's contact (or the object with itself)
    n = normal[c]  # from shape 0 toward shape 1
    # Newton's signed separation of the two surfaces (contact_surface_separation): < 0 overlaps.
    separation = wp.dot(n, p1 - p0) - (margin0[c] + margin1[c])
    if separation >= 0.0:
        return
    depth = -separation
    w = w1
    away = n
    if w1 < 0:
        w = w0
        away = -n
    wp.atomic_add(push_sum, w, (depth * depth) * away)
    wp.atomic_add(depth_sum, w, depth)


def separate_objects(d: Worlds, worlds: torch.Tensor | np.ndarray, passes: int = 6) -> None:
    """Move the object of each world in ``worlds`` (G, K) bool out of whatever it overlaps (the
    hand, the table) by a translation along the contacts' normals, as far as the overlaps go; the
    robot, the rotation and the velocities stay. ``passes`` rounds of collision detection: a
    corner pushed out of the palm may meet a finger. Torch work runs on the current stream: the
    caller puts it on the worlds' own."""
    n = d.dims
    worlds = worlds.cpu() if isinstance(worlds, torch.Tensor) else worlds
    sel = torch.as_tensor(np.asarray(worlds), dtype=torch.bool)
    if sel.shape != (n.G, n.K):
        raise ValueError(f"worlds: expected shape ({n.G}, {n.K}), got {tuple(sel.shape)}")
    flags = sel.reshape(n.W).numpy()
    device = d.model.device
    moving = sel.to(wp.device_to_torch(device))[..., None]
    c = d.contacts
    with wp.ScopedDevice(device):
        articulations = wp.array(flags[d.model.articulation_world.numpy()], dtype=bool)
        push_sum = wp.zeros(n.W, dtype=wp.vec3)
        depth_sum = wp.zeros(n.W, dtype=wp.float32)
        push = wp.to_torch(push_sum).view(n.G, n.K, 3)
        depth = wp.to_torch(depth_sum).view(n.G, n.K, 1)
        st = d.state_0
        for _ in range(passes):
            newton.eval_fk(d.model, st.joint_q, st.joint_qd, st, mask=articulations)
            d.pipeline.collide(st, d.contacts)
            push_sum.zero_()
            depth_sum.zero_()
            wp.launch(
                object_push,
                dim=c.rigid_contact_max,
                inputs=[
                    *contact_points(c),
                    c.rigid_contact_point1,
                    c.rigid_contact_normal,
                    c.rigid_contact_margin0,
                    c.rigid_contact_margin1,
                    d.model.shape_body,
                    st.body_q,
                    d.index.object_world,
                ],
                outputs=[push_sum, depth_sum],
            )
            step = torch.where(moving, push / depth.clamp_min(1e-9), 0.0)
            for state in (d.state_0, d.state_1):
                wp.to_torch(state.joint_q).view(n.G, n.K, n.coords)[..., n.free_coords][..., :3] += step
        for state in (d.state_0, d.state_1):
            newton.eval_fk(d.model, state.joint_q, state.joint_qd, state, mask=articulations)
        if d.config.collision == "mujoco":
            # The solver exports its own contacts into this buffer: surface points, no offsets.
            c.rigid_contact_offset0.zero_()
            c.rigid_contact_offset1.zero_()
