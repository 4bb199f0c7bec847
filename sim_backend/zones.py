"""Touch zones: regions of the robot's links that report one normal force each, as touch arrays,
pressure pads and taxel skins do. Their boxes indexed by the link that carries them, and the
kernel that sums each world's contact normal forces inside them, in the captured frame."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import warp as wp

if TYPE_CHECKING:
    from .population import Population

__all__ = ["accumulate_zones", "zone_arrays"]


@wp.kernel(enable_backward=False)
def accumulate_zones(
    contact_count: wp.array[wp.int32],
    shape0: wp.array[wp.int32],
    shape1: wp.array[wp.int32],
    point0: wp.array[wp.vec3],
    normal: wp.array[wp.vec3],
    contact_force: wp.array[wp.spatial_vector],
    shape_body: wp.array[wp.int32],
    body_q: wp.array[wp.transform],
    object_world: wp.array[wp.int32],
    bodies_per_world: int,
    zone_first: wp.array[wp.int32],
    zone_index: wp.array[wp.int32],
    zone_center: wp.array[wp.vec3],
    zone_half: wp.array[wp.vec3],
    touch: wp.array2d[float],
):
    """Sum, per touch zone, the normal force of its world's object on the contacts inside the zone's
    box (as a touch array reports: the normal force on each cell, whatever slides along it).

    ``zone_first[b]`` .. ``zone_first[b + 1]`` are the zones on the world's local body b, in
    ``zone_index`` (the zone's place in the record), ``zone_center`` and ``zone_half`` (its box in
    the link's frame). Launch dim: contact capacity."""
    c = wp.tid()
    if c >= contact_count[0]:
        return
    b0 = shape_body[shape0[c]]
    b1 = shape_body[shape1[c]]
    if b0 < 0 or b1 < 0:
        return
    obj = b1
    link = b0
    if object_world[b0] >= 0:
        obj = b0
        link = b1
    w = object_world[obj]
    if w < 0 or object_world[link] >= 0:
        return
    local = link - w * bodies_per_world
    if local < 0 or local >= bodies_per_world:
        return
    first = zone_first[local]
    last = zone_first[local + 1]
    if first == last:
        return
    pressed = wp.abs(wp.dot(wp.spatial_top(contact_force[c]), wp.normalize(normal[c])))
    if pressed == 0.0:  # inside the detection gap, not touching
        return
    p = wp.transform_point(wp.transform_inverse(body_q[link]), wp.transform_point(body_q[b0], point0[c]))
    for i in range(first, last):
        d = p - zone_center[i]
        h = zone_half[i]
        if wp.abs(d[0]) <= h[0] and wp.abs(d[1]) <= h[1] and wp.abs(d[2]) <= h[2]:
            wp.atomic_add(touch, w, zone_index[i], pressed)


def zone_arrays(pop: Population) -> dict[str, wp.array]:
    """The touch zones by the local body that carries them (CSR: ``zone_first`` has one entry
    per body and one more), with their place in the record and their boxes."""
    lay = pop.layout
    order = np.argsort(lay.zone_bodies, kind="stable")
    first = np.searchsorted(lay.zone_bodies[order], np.arange(pop.bodies + 1)).astype(np.int32)
    boxes = lay.zone_boxes[order].reshape(-1, 6)
    return {
        "zone_first": wp.array(first, dtype=wp.int32),
        "zone_index": wp.array(order.astype(np.int32), dtype=wp.int32),
        "zone_center": wp.array(boxes[:, :3].copy(), dtype=wp.vec3),
        "zone_half": wp.array(boxes[:, 3:].copy(), dtype=wp.vec3),
    }
