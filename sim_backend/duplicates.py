"""Contacts that Newton's narrow phase emits twice, made inert before the solver sees them.

Newton 1.8's primitive narrow phase can write one touch twice (box-box and capsule-box, the shapes
of most hands and blocks): the same shape pair, the same points and normal. MuJoCo takes each as a
contact of its own, so that touch is twice as stiff as the robot file's engine makes it (MuJoCo C
writes it once). Found comparing a world with MuJoCo C on the Shadow hand's block scene; reduced to
a two-body scene in tests/test_duplicate_contacts.py, which fails once Newton stops doing it.
"""

from __future__ import annotations

import warp as wp

__all__ = ["LOOK_BACK", "drop_duplicate_contacts"]

LOOK_BACK = 8
"""How many contacts before each one it is compared with: a shape pair's contacts are written
together (one narrow-phase thread per pair), at most a handful of them."""
_SAME = 1e-5
"""Points closer than this are one point [m] (the copies agree to float rounding)."""
_AWAY = -1.0
"""The margin that moves a copy a metre out: past every solver row and every reading."""


@wp.kernel(enable_backward=False)
def _drop_copies(
    count: wp.array[wp.int32],
    shape0: wp.array[wp.int32],
    shape1: wp.array[wp.int32],
    point0: wp.array[wp.vec3],
    point1: wp.array[wp.vec3],
    normal: wp.array[wp.vec3],
    margin0: wp.array[wp.float32],
):
    i = wp.tid()
    if i >= count[0]:
        return
    for k in range(1, LOOK_BACK + 1):
        j = i - k
        if j < 0:
            return
        if shape0[j] == shape0[i] and shape1[j] == shape1[i]:
            if (
                wp.length(point0[j] - point0[i]) < _SAME
                and wp.length(point1[j] - point1[i]) < _SAME
                and wp.dot(normal[j], normal[i]) > 0.9999
            ):
                # The first of a run of copies has no earlier twin, so one always stays. Moved out
                # rather than removed: the buffer keeps its count inside the captured graph.
                margin0[i] = _AWAY
                return


def drop_duplicate_contacts(contacts) -> None:
    """Make every contact in ``contacts`` (newton.Contacts) that repeats one written just before it
    inert: same shapes, same points, same normal. No host work: safe inside a captured graph."""
    c = contacts
    wp.launch(
        _drop_copies,
        dim=c.rigid_contact_max,
        inputs=[
            c.rigid_contact_count,
            c.rigid_contact_shape0,
            c.rigid_contact_shape1,
            c.rigid_contact_point0,
            c.rigid_contact_point1,
            c.rigid_contact_normal,
        ],
        outputs=[c.rigid_contact_margin0],
    )
