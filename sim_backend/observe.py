"""Observation kernels: what each world's robot would sense, computed on the device.

All kernels run inside the captured frame graph after the last substep. Per world ``w`` and
sensor ``l`` they produce the paper's observation o_t: joint positions, sensor poses, the contact
force in the sensor frame, translational slip (flag + unit direction in the sensor's tangent
plane) and rotational slip (flag + sense), plus the object pose and a health flag.

Sensor frame convention: z is the pad's outward normal, x points along the finger (distal), so
the tangent plane is the sensor's x-y plane.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
import warp as wp

from .health import count_object_contact
from .zones import press_zones

__all__ = [
    "Buffers",
    "Observation",
    "accumulate_contacts",
    "add_sensor_noise",
    "allocate_buffers",
    "finish_observation",
    "gather_joints",
    "launch_finish",
    "observation_views",
    "sensor_poses",
    "touch_from_sums",
]


@wp.kernel(enable_backward=False)
def gather_joints(
    joint_q: wp.array[float],
    coords_per_world: int,
    coord_index: wp.array[wp.int32],
    q_out: wp.array2d[float],
):
    """q_out[w, d] = joint_q of actuated joint d in world w. Launch dim (W, D)."""
    w, d = wp.tid()
    q_out[w, d] = joint_q[w * coords_per_world + coord_index[d]]


@wp.kernel(enable_backward=False)
def sensor_poses(
    body_q: wp.array[wp.transform],
    bodies_per_world: int,
    sensor_body: wp.array[wp.int32],
    sensor_offset: wp.array[wp.transform],
    pos_out: wp.array2d[wp.vec3],
    rot_out: wp.array2d[wp.quat],
    force_acc: wp.array2d[wp.vec3],
    slip_acc: wp.array2d[wp.vec3],
    spin_acc: wp.array2d[wp.vec3],
    weight_acc: wp.array2d[float],
):
    """World pose of every sensor frame; clears the contact accumulators. Launch dim (W, L)."""
    w, l = wp.tid()
    x = wp.transform_multiply(body_q[w * bodies_per_world + sensor_body[l]], sensor_offset[l])
    pos_out[w, l] = wp.transform_get_translation(x)
    rot_out[w, l] = wp.transform_get_rotation(x)
    force_acc[w, l] = wp.vec3(0.0)
    slip_acc[w, l] = wp.vec3(0.0)
    spin_acc[w, l] = wp.vec3(0.0)
    weight_acc[w, l] = 0.0


@wp.func
def _point_velocity(body_q: wp.transform, body_qd: wp.spatial_vector, com: wp.vec3, p: wp.vec3) -> wp.vec3:
    # body_qd holds the COM's linear velocity and the angular velocity, both in the world frame.
    com_world = wp.transform_point(body_q, com)
    return wp.spatial_top(body_qd) + wp.cross(wp.spatial_bottom(body_qd), p - com_world)


@wp.func
def _between_surfaces(b0: int, b1: int, a: wp.vec3, b: wp.vec3, body_q: wp.array[wp.transform]) -> wp.vec3:
    """The world point halfway between a contact's surface points ``a`` on body ``b0`` and ``b`` on
    ``b1`` (body frames; a static shape's, the table's, in the world frame), where MuJoCo puts a
    contact. Newton gives each shape's point on its core (a capsule's axis, a sphere's centre) and
    the offset to its surface: on the axis, a phalanx's contacts lay on the edge its four touch
    zones share."""
    if b0 >= 0:
        a = wp.transform_point(body_q[b0], a)
    if b1 >= 0:
        b = wp.transform_point(body_q[b1], b)
    return 0.5 * (a + b)


@wp.kernel(enable_backward=False)
def accumulate_contacts(
    contact_count: wp.array[wp.int32],
    shape0: wp.array[wp.int32],
    shape1: wp.array[wp.int32],
    point0: wp.array[wp.vec3],
    point1: wp.array[wp.vec3],
    offset0: wp.array[wp.vec3],
    offset1: wp.array[wp.vec3],
    normal: wp.array[wp.vec3],
    contact_force: wp.array[wp.spatial_vector],
    shape_body: wp.array[wp.int32],
    body_q: wp.array[wp.transform],
    body_qd: wp.array[wp.spatial_vector],
    body_com: wp.array[wp.vec3],
    sensor_row: wp.array[wp.int32],
    object_world: wp.array[wp.int32],
    sensor_count: int,
    bodies_per_world: int,
    zone_first: wp.array[wp.int32],
    zone_index: wp.array[wp.int32],
    zone_center: wp.array[wp.vec3],
    zone_half: wp.array[wp.vec3],
    force_acc: wp.array2d[wp.vec3],
    slip_acc: wp.array2d[wp.vec3],
    spin_acc: wp.array2d[wp.vec3],
    weight_acc: wp.array2d[float],
    touch: wp.array2d[float],
    hand_contacts: wp.array[wp.int32],
    rest_contacts: wp.array[wp.int32],
):
    """Sum, per sensor, the force from its world's object and the force-weighted slip velocity;
    per touch zone, the normal force of every contact inside it, the object's or not
    (:func:`.zones.press_zones`); per world, the object's contacts with the robot's links (within
    the detection gap) and those that press it against the static scene.

    ``sensor_row[b]`` is w * L + l when body b carries sensor l of world w, else -1;
    ``object_world[b]`` is w when body b is world w's object, else -1. Launch dim: contact capacity.
    """
    c = wp.tid()
    if c >= contact_count[0]:
        return
    b0 = shape_body[shape0[c]]
    b1 = shape_body[shape1[c]]
    # contact_force is the force on shape 0; flip it when the sensor is shape 1.
    f = wp.spatial_top(contact_force[c])
    touched = _between_surfaces(b0, b1, point0[c] + offset0[c], point1[c] + offset1[c], body_q)
    press_zones(b0, b1, f, normal[c], touched, body_q, object_world, bodies_per_world,
                zone_first, zone_index, zone_center, zone_half, touch)  # fmt: skip
    count_object_contact(b0, b1, wp.length(f), object_world, hand_contacts, rest_contacts)
    if b0 < 0 or b1 < 0:
        return
    # The pads' slip velocity stays at shape 0's core point (a pad's centre), where the bundled
    # recordings measured it and the slip thresholds were set.
    point = wp.transform_point(body_q[b0], point0[c])
    sensor = b0
    obj = b1
    sign = 1.0
    if sensor_row[b0] < 0:
        sensor = b1
        obj = b0
        sign = -1.0
    row = sensor_row[sensor]
    if row < 0 or object_world[obj] < 0:
        return
    f = sign * f
    weight = wp.length(f)
    if weight == 0.0:  # inside the detection gap, not touching
        return
    w = row // sensor_count
    l = row - w * sensor_count
    v_rel = _point_velocity(body_q[sensor], body_qd[sensor], body_com[sensor], point) - _point_velocity(
        body_q[obj], body_qd[obj], body_com[obj], point
    )
    n = wp.normalize(normal[c])
    v_tan = v_rel - wp.dot(v_rel, n) * n
    omega_rel = wp.spatial_bottom(body_qd[sensor]) - wp.spatial_bottom(body_qd[obj])
    wp.atomic_add(force_acc, w, l, f)
    wp.atomic_add(slip_acc, w, l, weight * v_tan)
    wp.atomic_add(spin_acc, w, l, weight * omega_rel)
    wp.atomic_add(weight_acc, w, l, weight)


@wp.kernel(enable_backward=False)
def finish_observation(
    rot: wp.array2d[wp.quat],
    force_acc: wp.array2d[wp.vec3],
    slip_acc: wp.array2d[wp.vec3],
    spin_acc: wp.array2d[wp.vec3],
    weight_acc: wp.array2d[float],
    slip_speed: float,
    spin_speed: float,
    force_out: wp.array2d[wp.vec3],
    slip_out: wp.array2d[float],
    slip_dir_out: wp.array2d[wp.vec2],
    spin_out: wp.array2d[float],
    spin_sense_out: wp.array2d[float],
):
    """Rotate into the sensor frame and threshold the slip speeds. Launch dim (W, L)."""
    w, l = wp.tid()
    r = rot[w, l]
    force_out[w, l] = wp.quat_rotate_inv(r, force_acc[w, l])
    slip = 0.0
    d = wp.vec2(0.0, 0.0)
    spin = 0.0
    sense = 0.0
    total = weight_acc[w, l]
    if total > 0.0:
        v = wp.quat_rotate_inv(r, slip_acc[w, l] / total)
        speed = wp.length(wp.vec2(v[0], v[1]))
        if speed > slip_speed:
            slip = 1.0
            d = wp.vec2(v[0], v[1]) / speed
        # Spin of the pad against the object about the pad normal (sensor z); the sense is 1 for
        # counter-clockwise (right hand about +z), else 0, as the paper's r in {0, 1}.
        s = wp.quat_rotate_inv(r, spin_acc[w, l] / total)[2]
        if wp.abs(s) > spin_speed:
            spin = 1.0
            if s > 0.0:
                sense = 1.0
    slip_out[w, l] = slip
    slip_dir_out[w, l] = d
    spin_out[w, l] = spin
    spin_sense_out[w, l] = sense


# ---------------------------------------------------------------------- what the kernels write
@dataclass
class Observation:
    """What every world's robot senses after a frame; torch views of device memory.

    G groups, K worlds, D actuated joints, L fingertip sensors, Z touch zones. Frames follow
    :mod:`sim_backend.observe`: sensor z is the pad normal, the tangent plane its x-y plane.
    """

    q: torch.Tensor
    """Joint positions, shape (G, K, D) [rad or m]."""
    sensor_pos: torch.Tensor
    """Sensor positions in the world frame, shape (G, K, L, 3) [m]."""
    sensor_rot: torch.Tensor
    """Sensor orientations in the world frame, shape (G, K, L, 4), quaternion (x, y, z, w)."""
    force: torch.Tensor
    """Contact force of the object on each sensor, in the sensor frame, shape (G, K, L, 3) [N]."""
    slip: torch.Tensor
    """Translational slip flag, shape (G, K, L), 1.0 slipping / 0.0 not."""
    slip_dir: torch.Tensor
    """Unit direction the pad slides over the object, in the sensor's tangent plane, shape (G, K, L, 2);
    zero when not slipping."""
    spin: torch.Tensor
    """Rotational slip flag, shape (G, K, L), 1.0 / 0.0."""
    spin_sense: torch.Tensor
    """Rotational slip sense about the pad normal, shape (G, K, L): 1.0 counter-clockwise, else 0.0."""
    touch: torch.Tensor
    """Normal force of the object on each touch zone, shape (G, K, Z) [N]."""
    object_pose: torch.Tensor
    """Object pose in the world frame, shape (G, K, 7): position [m], quaternion (x, y, z, w)."""
    health: torch.Tensor
    """Per-world health, shape (G, K), int32: :data:`.health.HEALTH_OK`, HEALTH_NAN, HEALTH_LOST or HEALTH_AWAY."""


@dataclass
class Buffers:
    """Warp arrays behind :class:`Observation` and the contact accumulators, leading axis W."""

    q: wp.array
    sensor_pos: wp.array
    sensor_rot: wp.array
    force: wp.array
    slip: wp.array
    slip_dir: wp.array
    spin: wp.array
    spin_sense: wp.array
    touch: wp.array
    object_pose: wp.array
    health: wp.array
    force_acc: wp.array
    slip_acc: wp.array
    spin_acc: wp.array
    weight_acc: wp.array
    hand_contacts: wp.array
    """Contacts of each world's object with the robot's links this frame, (W,) int32."""
    rest_contacts: wp.array
    """Contacts pressing each world's object against the static scene this frame, (W,) int32."""
    wrench: wp.array
    """Perturbation wrench on each world's object for the next frame, (W,) spatial_vector."""


def allocate_buffers(w: int, d: int, l: int, zones: int = 0) -> Buffers:
    """Zeroed buffers for ``w`` worlds of ``d`` joints, ``l`` sensors and ``zones`` touch zones."""
    z = wp.zeros
    return Buffers(
        q=z((w, d), dtype=float),
        sensor_pos=z((w, l), dtype=wp.vec3),
        sensor_rot=z((w, l), dtype=wp.quat),
        force=z((w, l), dtype=wp.vec3),
        slip=z((w, l), dtype=float),
        slip_dir=z((w, l), dtype=wp.vec2),
        spin=z((w, l), dtype=float),
        spin_sense=z((w, l), dtype=float),
        touch=z((w, zones), dtype=float),
        object_pose=z((w, 7), dtype=float),
        health=z(w, dtype=wp.int32),
        force_acc=z((w, l), dtype=wp.vec3),
        slip_acc=z((w, l), dtype=wp.vec3),
        spin_acc=z((w, l), dtype=wp.vec3),
        weight_acc=z((w, l), dtype=float),
        hand_contacts=z(w, dtype=wp.int32),
        rest_contacts=z(w, dtype=wp.int32),
        wrench=z(w, dtype=wp.spatial_vector),
    )


def observation_views(b: Buffers, g: int, k: int) -> Observation:
    """Torch views (no copies) of the observation buffers, leading axes (G, K)."""
    views = {}
    for f in fields(Observation):
        t = wp.to_torch(getattr(b, f.name))
        views[f.name] = t.view(g, k, *t.shape[1:])
    return Observation(**views)


def launch_finish(b: Buffers, slip_speed: float, spin_speed: float) -> None:
    """Launch :func:`finish_observation` over every world and sensor of ``b``."""
    w, l = b.force.shape
    wp.launch(
        finish_observation,
        dim=(w, l),
        inputs=[b.sensor_rot, b.force_acc, b.slip_acc, b.spin_acc, b.weight_acc, slip_speed, spin_speed],
        outputs=[b.force, b.slip, b.slip_dir, b.spin, b.spin_sense],
    )


def touch_from_sums(
    force: np.ndarray,
    slip: np.ndarray,
    spin: np.ndarray,
    weight: np.ndarray,
    slip_speed: float,
    spin_speed: float,
) -> dict[str, np.ndarray]:
    """:func:`finish_observation` on the host, for one robot whose contacts another engine
    reports: from the per-sensor sums in each sensor's frame (force [N], force-weighted slip
    velocity [N m/s] and relative angular velocity [N rad/s], total force ``weight`` [N], (L, 3)
    and (L,)) to the touch fields of :data:`protocol.SENSING`."""
    L = weight.shape[0]
    out = {
        "force": force.astype(np.float32),
        "slip": np.zeros(L, np.float32),
        "slip_dir": np.zeros((L, 2), np.float32),
        "spin": np.zeros(L, np.float32),
        "spin_sense": np.zeros(L, np.float32),
    }
    for l in np.flatnonzero(weight > 0):
        v = slip[l] / weight[l]
        speed = float(np.hypot(v[0], v[1]))
        if speed > slip_speed:
            out["slip"][l] = 1.0
            out["slip_dir"][l] = v[:2] / speed
        s = spin[l, 2] / weight[l]
        if abs(s) > spin_speed:
            out["spin"][l] = 1.0
            out["spin_sense"][l] = float(s > 0.0)
    return out


def add_sensor_noise(
    sensing: dict[str, np.ndarray | None],
    rng: np.random.Generator,
    joint_sigma: float = 0.0,
    force_sigma: float = 0.0,
    force_bias: float = 0.0,
    slip_miss: float = 0.0,
    touch_sigma: float = 0.0,
    touch_deadband: float = 0.0,
) -> None:
    """What real sensors add to a recording's sensing fields (F, G, ...), in place: Gaussian joint
    noise [rad or m]; force noise per axis and a bias per sensor and axis fixed per track [N], read
    only while in contact; missed slip and spin events (a fraction ``slip_miss`` of the flags);
    touch-zone noise [N] while pressed and a deadband [N] under which a zone reads 0, as a touch
    array's threshold does. A field the robot does not send (None) stays so."""
    q = sensing["q"]
    sensing["q"] = q + rng.normal(0.0, joint_sigma, q.shape).astype(np.float32)
    if (force := sensing["force"]) is not None:
        _, g, l, _ = force.shape
        bias = rng.normal(0.0, force_bias, (1, g, l, 3))
        touching = np.linalg.norm(force, axis=-1, keepdims=True) > 0  # a sensor reads noise only in contact
        sensing["force"] = (force + touching * (bias + rng.normal(0.0, force_sigma, force.shape))).astype(np.float32)
    for flags in (sensing["slip"], sensing["spin"]):
        if flags is not None:
            flags[rng.random(flags.shape) < slip_miss] = 0.0
    if (touch := sensing["touch"]) is not None and touch.size:
        pressed = touch > 0
        touch = np.maximum(touch + pressed * rng.normal(0.0, touch_sigma, touch.shape), 0.0)
        sensing["touch"] = np.where(touch < touch_deadband, 0.0, touch).astype(np.float32)
