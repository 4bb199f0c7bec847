"""Touch zones: regions of the robot's links that report one normal force each, as touch arrays,
pressure pads and taxel skins do. Their boxes indexed by the link that carries them, and the
function that adds each contact's normal force to the zones it lies in, called by the observation
kernel (:func:`.observe.accumulate_contacts`) in the captured frame."""

from __future__ import annotations

import numpy as np
import warp as wp

from .robot_specs import RobotLayout

__all__ = ["ZONE_EDGE", "press_zones", "zone_arrays"]

ZONE_EDGE = wp.constant(1e-4)
"""The rim of a zone's box [m]: a contact this close to a face, inside or out, presses one zone of
its link, the first whose rim holds it, unless another zone holds it well inside. Contact points
land exactly on faces (a block lying across the palm's edge, its contact points clipped to the
palm's face; a phalanx's front where its left and right zones meet), and float32 rounding put them
in none, one or both zones at random: the Allegro palm read 36-88 % of a resting block's weight."""


@wp.func
def press_zones(
    b0: int,
    b1: int,
    force: wp.vec3,
    normal: wp.vec3,
    point: wp.vec3,
    body_q: wp.array[wp.transform],
    object_world: wp.array[wp.int32],
    bodies_per_world: int,
    zone_first: wp.array[wp.int32],
    zone_index: wp.array[wp.int32],
    zone_center: wp.array[wp.vec3],
    zone_half: wp.array[wp.vec3],
    touch: wp.array2d[float],
):
    """Add one contact's normal force to the touch zones it lies in, on either body (``b0``,
    ``b1``; -1 for the table) at ``point`` (world frame). A touch array reports the normal force on
    each cell whatever presses it: the object, and as much the hand's own fingers, its palm or the
    table (a real skin cannot tell them apart; the scenes' touch sensors read 80-90 % of their
    force from the hand touching itself while it curls over a block).

    ``zone_first[b]`` .. ``zone_first[b + 1]`` are the zones on the world's local body b, in
    ``zone_index`` (the zone's place in the record), ``zone_center`` and ``zone_half`` (its box in
    the link's frame)."""
    pressed = wp.abs(wp.dot(force, wp.normalize(normal)))
    if pressed == 0.0:  # inside the detection gap, not touching
        return
    for side in range(2):
        link = b0
        if side == 1:
            link = b1
        if link < 0 or object_world[link] >= 0:  # the table, or an object: no zones
            continue
        w = link // bodies_per_world
        local = link - w * bodies_per_world
        p = wp.transform_point(wp.transform_inverse(body_q[link]), point)
        # Warp mutates in a loop only what was made by a constructor, not a literal.
        inner = int(0)  # noqa: UP018, RUF046
        rim = int(-1)  # noqa: UP018, RUF046
        for i in range(zone_first[local], zone_first[local + 1]):
            d = p - zone_center[i]
            h = zone_half[i]
            # How far inside the box's nearest face the point lies [m] (negative outside).
            depth = wp.min(wp.min(h[0] - wp.abs(d[0]), h[1] - wp.abs(d[1])), h[2] - wp.abs(d[2]))
            if depth > ZONE_EDGE:
                wp.atomic_add(touch, w, zone_index[i], pressed)
                inner += 1
            elif depth >= -ZONE_EDGE and rim < 0:
                rim = i
        if inner == 0 and rim >= 0:
            wp.atomic_add(touch, w, zone_index[rim], pressed)


def zone_arrays(lay: RobotLayout, bodies: int) -> dict[str, wp.array]:
    """The touch zones by the local body that carries them (CSR: ``zone_first`` has one entry
    per body of a world's ``bodies`` and one more), with their place in the record and their boxes."""
    order = np.argsort(lay.zone_bodies, kind="stable")
    first = np.searchsorted(lay.zone_bodies[order], np.arange(bodies + 1)).astype(np.int32)
    boxes = lay.zone_boxes[order].reshape(-1, 6)
    return {
        "zone_first": wp.array(first, dtype=wp.int32),
        "zone_index": wp.array(order.astype(np.int32), dtype=wp.int32),
        "zone_center": wp.array(boxes[:, :3].copy(), dtype=wp.vec3),
        "zone_half": wp.array(boxes[:, 3:].copy(), dtype=wp.vec3),
    }
