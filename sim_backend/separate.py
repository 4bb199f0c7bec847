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

import warp as wp

__all__ = ["object_push"]


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
