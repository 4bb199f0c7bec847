"""Whether each world still holds its object: the object's contacts with the hand and with the
static scene, counted by the observation kernel (:func:`.observe.accumulate_contacts`), and each
world's health from its object's pose, speed and those counts, in the captured frame."""

from __future__ import annotations

import warp as wp

__all__ = ["HEALTH_AWAY", "HEALTH_LOST", "HEALTH_NAN", "HEALTH_OK", "count_object_contact", "object_health"]

HEALTH_OK = 0
HEALTH_NAN = 1
"""A world's state holds NaN or Inf."""
HEALTH_LOST = 2
"""A world's object fell through the table or flies off faster than anything held (it exploded)."""
HEALTH_AWAY = 3
"""A world's object lies far from the hand, or (for a hand that carries objects on its palm) rests
on the scene and touches no link of the hand, but is otherwise plausible: above the table and
slower than an explosion. Lost while the real hand holds the object; a valid hypothesis when it
does not (the object was put down, or dropped, and the hand moved on), which only the tracker knows."""


@wp.func
def count_object_contact(
    b0: int,
    b1: int,
    pressed: float,
    object_world: wp.array[wp.int32],
    hand_contacts: wp.array[wp.int32],
    rest_contacts: wp.array[wp.int32],
):
    """Count a contact of a world's object: with a body of its world (a link of the hand) in
    ``hand_contacts``, even inside the detection gap; with the static scene (body -1: the table)
    in ``rest_contacts`` only where it presses."""
    obj = -1
    other = b1
    if b0 >= 0:
        if object_world[b0] >= 0:
            obj = b0
    if obj < 0 and b1 >= 0:
        if object_world[b1] >= 0:
            obj = b1
            other = b0
    if obj < 0:
        return
    if other >= 0:
        wp.atomic_add(hand_contacts, object_world[obj], 1)
    elif pressed > 0.0:
        wp.atomic_add(rest_contacts, object_world[obj], 1)


@wp.kernel(enable_backward=False)
def object_health(
    body_q: wp.array[wp.transform],
    body_qd: wp.array[wp.spatial_vector],
    joint_q: wp.array[float],
    bodies_per_world: int,
    coords_per_world: int,
    object_body: int,
    sensor_pos: wp.array2d[wp.vec3],
    sensor_count: int,
    floor_z: float,
    lost_distance: float,
    lost_speed: float,
    hand_contacts: wp.array[wp.int32],
    rest_contacts: wp.array[wp.int32],
    on_palm: int,
    pose_out: wp.array2d[float],
    health_out: wp.array[wp.int32],
):
    """Object pose (x, y, z, qx, qy, qz, qw) and health of each world. Launch dim (W,).
    ``on_palm``: the hand carries objects on its palm, so an object resting on the scene
    (``rest_contacts``) that touches no link (``hand_contacts``) has left it, however near."""
    w = wp.tid()
    x = body_q[w * bodies_per_world + object_body]
    qd = body_qd[w * bodies_per_world + object_body]
    p = wp.transform_get_translation(x)
    q = wp.transform_get_rotation(x)
    pose_out[w, 0] = p[0]
    pose_out[w, 1] = p[1]
    pose_out[w, 2] = p[2]
    pose_out[w, 3] = q[0]
    pose_out[w, 4] = q[1]
    pose_out[w, 5] = q[2]
    pose_out[w, 6] = q[3]
    finite = wp.isfinite(p) and wp.isfinite(wp.vec4(q[0], q[1], q[2], q[3])) and wp.isfinite(qd)
    for i in range(coords_per_world):
        finite = finite and wp.isfinite(joint_q[w * coords_per_world + i])
    centre = wp.vec3(0.0)
    for l in range(sensor_count):
        centre += sensor_pos[w, l]
    centre = centre / float(sensor_count)
    health = HEALTH_OK
    if not finite:
        health = HEALTH_NAN
    elif p[2] < floor_z or wp.length(wp.spatial_top(qd)) > lost_speed:
        health = HEALTH_LOST
    elif wp.length(p - centre) > lost_distance:
        health = HEALTH_AWAY
    elif on_palm != 0 and rest_contacts[w] > 0 and hand_contacts[w] == 0:
        health = HEALTH_AWAY
    health_out[w] = health
