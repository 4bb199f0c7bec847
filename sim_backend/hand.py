"""The procedural Allegro-like hand on a 6-DoF wrist, written from the real hand's published
kinematics: link lengths, joint limits and masses, box and capsule collision, position servos."""

from __future__ import annotations

import math

import newton
import numpy as np
import warp as wp

from .robot_specs import HandSpec, RobotLayout, joint_coord_dof, zone_layout

__all__ = [
    "ALLEGRO_FINGER_LIMITS",
    "ALLEGRO_FINGER_LINKS",
    "ALLEGRO_FINGER_MASSES",
    "ALLEGRO_THUMB_LIMITS",
    "ALLEGRO_THUMB_LINKS",
    "TIP_RADIUS",
    "add_hand",
]

# Joint limits of the real Allegro hand v4 [rad], per finger joint 0..3 (index, middle, ring)
# and for the thumb joints 12..15.
ALLEGRO_FINGER_LIMITS = ((-0.47, 0.47), (-0.196, 1.61), (-0.174, 1.709), (-0.227, 1.618))
ALLEGRO_THUMB_LIMITS = ((0.263, 1.396), (-0.105, 1.163), (-0.189, 1.644), (-0.162, 1.719))
# Link lengths of the real Allegro hand [m]: base (abduction) link, proximal, middle, distal.
ALLEGRO_FINGER_LINKS = (0.0164, 0.054, 0.0384, 0.0267)
ALLEGRO_THUMB_LINKS = (0.0177, 0.0514, 0.0423)
# Link masses from the Allegro URDF [kg].
ALLEGRO_FINGER_MASSES = (0.0119, 0.065, 0.0355, 0.0264)

_PALM_HALF = (0.0204, 0.0565, 0.0475)  # palm half extents [m]: thickness, width, length
_FINGER_Y = (0.0435, 0.0, -0.0435)  # finger base offsets across the palm [m]
_LINK_RADIUS = 0.0098
TIP_RADIUS = 0.012
"""Radius of the fingertip spheres [m]."""
_WRIST_LIMITS = ((-0.6, 0.6), (-0.6, 0.6), (0.0, 0.8), (-math.pi, math.pi), (-math.pi, math.pi), (-math.pi, math.pi))
_WRIST_NAMES = ("wrist_x", "wrist_y", "wrist_z", "wrist_yaw", "wrist_pitch", "wrist_roll")


def _quat_axis_angle(axis: tuple[float, float, float], angle: float) -> wp.quat:
    return wp.quat_from_axis_angle(wp.vec3(*axis), angle)


def _axis(axis, lim: tuple[float, float], drive: tuple[float, float, float, float]) -> dict:
    """A joint axis with its limits and its position servo ``drive`` (stiffness, damping, effort
    limit, armature), as Newton's joint builders take them."""
    ke, kd, effort, armature = drive
    return {
        "axis": wp.vec3(*axis),
        "limit_lower": lim[0],
        "limit_upper": lim[1],
        "target_ke": ke,
        "target_kd": kd,
        "effort_limit": effort,
        "armature": armature,
        "actuator_mode": newton.JointTargetMode.POSITION,
    }


class _HandBuilder:
    """Adds the hand's links, joints and shapes to one world's builder, recording its layout."""

    def __init__(self, builder: newton.ModelBuilder, spec: HandSpec):
        self.builder, self.spec = builder, spec
        self.body_start = builder.body_count
        self.gravcomp = {"mujoco:gravcomp": 1.0} if spec.gravity_compensation else None
        # Hand shapes never collide with each other (collision group -1 on every shape): the fingers
        # are kept apart by their joint limits, and self contacts would only slow the solver down.
        self.shape_cfg = newton.ModelBuilder.ShapeConfig(density=0.0, collision_group=-1, mu=1.0)
        # (stiffness, damping, effort limit, armature) of the wrist's and the fingers' position drives
        self.wrist_drive = (spec.wrist_ke, spec.wrist_kd, 1e3, 0.01)
        self.finger_drive = (spec.finger_ke, spec.finger_kd, spec.finger_effort, spec.armature)
        self.names: list[str] = []
        self.lower: list[float] = []
        self.upper: list[float] = []
        self.joints: list[int] = []
        self.tips: list[int] = []
        self.bodies: dict[str, int] = {}
        """Each link's body index in the world, by its label."""

    def link(self, mass: float, inertia_diag: float, label: str) -> int:
        inertia = wp.mat33(inertia_diag, 0.0, 0.0, 0.0, inertia_diag, 0.0, 0.0, 0.0, inertia_diag)
        body = self.builder.add_link(mass=mass, inertia=inertia, label=label, custom_attributes=self.gravcomp)
        self.bodies[label] = body - self.body_start
        return body

    def hinge(self, parent: int, child: int, axis, lim, name: str, offset=(0.0, 0.0, 0.0), turn=None) -> int:
        """A finger hinge with the fingers' servo, at ``offset`` [m] (and ``turn``) in the parent's frame."""
        j = self.builder.add_joint_revolute(
            parent,
            child,
            parent_xform=wp.transform(wp.vec3(*offset), turn if turn is not None else wp.quat_identity()),
            label=name,
            **_axis(axis, lim, self.finger_drive),
        )
        self.joints.append(j)
        self.names.append(name)
        self.lower.append(lim[0])
        self.upper.append(lim[1])
        return j

    def capsule_link(self, length: float, mass: float, label: str) -> int:
        body = self.link(mass, mass * length * length / 12.0 + 1e-6, label)
        self.builder.add_shape_capsule(
            body,
            xform=wp.transform(wp.vec3(0.0, 0.0, 0.5 * length), wp.quat_identity()),
            radius=_LINK_RADIUS,
            half_height=max(0.5 * length - _LINK_RADIUS, 1e-3),
            cfg=self.shape_cfg,
            label=label,
        )
        return body

    def distal_link(self, parent_len: float, mass: float, label: str) -> int:
        body = self.capsule_link(parent_len, mass, label)
        self.builder.add_shape_sphere(
            body,
            xform=wp.transform(wp.vec3(0.0, 0.0, parent_len), wp.quat_identity()),
            radius=TIP_RADIUS,
            cfg=self.shape_cfg,
            label=f"{label}_tip",
        )
        return body

    def wrist_and_palm(self) -> int:
        """The palm on the wrist: slides along world x, y, z, then yaw, pitch, roll, as one joint of
        six axes. It stands in for an arm and has no links of its own: a chain of six single-axis
        joints moves the same, but is five levels deeper, and the solver's passes over the tree
        launch once per level and substep. Returns the palm's body."""
        # The palm frame: x = palm normal (towards the face), z = along the fingers. Turning it by
        # +90 deg about y makes the palm face world -z with the fingers along world +x.
        to_palm = _quat_axis_angle((0, 1, 0), math.pi / 2)
        palm = self.link(self.spec.palm_mass, 1e-3, "palm")
        # The roll turns about the palm frame's x, which is world -z before the palm's turn.
        axes = ((1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, 1), (0, 1, 0), (0, 0, -1))
        dofs = [
            newton.ModelBuilder.JointDofConfig(**_axis(a, lim, self.wrist_drive))
            for a, lim in zip(axes, _WRIST_LIMITS, strict=True)
        ]
        inverse_turn = wp.transform(wp.vec3(), wp.quat_inverse(to_palm))
        wrist = self.builder.add_joint_d6(
            -1, palm, linear_axes=dofs[:3], angular_axes=dofs[3:], child_xform=inverse_turn, label="wrist"
        )
        self.joints.append(wrist)
        self.names.extend(_WRIST_NAMES)
        self.lower.extend(lim[0] for lim in _WRIST_LIMITS)
        self.upper.extend(lim[1] for lim in _WRIST_LIMITS)
        hx, hy, hz = _PALM_HALF
        self.builder.add_shape_box(palm, hx=hx, hy=hy, hz=hz, cfg=self.shape_cfg, label="palm")
        return palm

    def finger(self, palm: int, name: str, y: float) -> None:
        """A finger of four links, its base ``y`` [m] across the palm's far edge."""
        l0, l1, l2, l3 = ALLEGRO_FINGER_LINKS
        m0, m1, m2, m3 = ALLEGRO_FINGER_MASSES
        lim = ALLEGRO_FINGER_LIMITS
        b0 = self.capsule_link(l0, m0, f"{name}_link0")
        self.hinge(palm, b0, (1, 0, 0), lim[0], f"{name}_0", offset=(0.0, y, _PALM_HALF[2]))
        b1 = self.capsule_link(l1, m1, f"{name}_link1")
        self.hinge(b0, b1, (0, 1, 0), lim[1], f"{name}_1", offset=(0.0, 0.0, l0))
        b2 = self.capsule_link(l2, m2, f"{name}_link2")
        self.hinge(b1, b2, (0, 1, 0), lim[2], f"{name}_2", offset=(0.0, 0.0, l1))
        b3 = self.distal_link(l3, m3, f"{name}_link3")
        self.hinge(b2, b3, (0, 1, 0), lim[3], f"{name}_3", offset=(0.0, 0.0, l2))
        self.tips.append(b3)

    def thumb(self, palm: int) -> None:
        """The thumb: its base sits on the palm's face near the wrist, on the index side. Joint 12
        turns it about the palm's long axis from pointing sideways (+y) to pointing out of the face
        (+x); joint 13 twists it about its own axis; joints 14, 15 curl it towards the fingers (+z)."""
        lim = ALLEGRO_THUMB_LIMITS
        t1, t2, t3 = ALLEGRO_THUMB_LINKS
        b12 = self.link(0.0176, 1e-5, "thumb_link0")
        self.hinge(palm, b12, (0, 0, -1), lim[0], "thumb_0", offset=(_PALM_HALF[0], 0.02, -0.035))
        self.builder.add_shape_sphere(b12, radius=_LINK_RADIUS, cfg=self.shape_cfg, label="thumb_link0")
        # Links below run along local +y (the thumb's axis before joint 12 turns it).
        to_y = _quat_axis_angle((1, 0, 0), -math.pi / 2)  # maps local +z onto +y
        b13 = self.capsule_link(t1, 0.0119, "thumb_link1")
        self.hinge(b12, b13, (0, 0, 1), lim[1], "thumb_1", turn=to_y)
        b14 = self.capsule_link(t2, 0.038, "thumb_link2")
        # After the to_y turn the link frame's x is still the palm normal; turning about it carries
        # the thumb's axis (local z, the palm's +y) towards the palm's +z, the fingers.
        self.hinge(b13, b14, (1, 0, 0), lim[2], "thumb_2", offset=(0.0, 0.0, t1))
        b15 = self.distal_link(t3, 0.0388, "thumb_link3")
        self.hinge(b14, b15, (1, 0, 0), lim[3], "thumb_3", offset=(0.0, 0.0, t2))
        self.tips.append(b15)

    def layout(self) -> RobotLayout:
        self.builder.add_articulation(self.joints, label=self.spec.name)
        coord, dof = joint_coord_dof(self.builder, self.joints)
        low, up = np.asarray(self.lower), np.asarray(self.upper)
        if self.spec.default_q:
            default_q = np.asarray(self.spec.default_q, dtype=np.float64)
        else:
            default_q = np.clip(np.zeros(len(self.names)), low, up)
            default_q[2] = 0.3
            default_q[6 + 12] = 0.263
        # Sensor frames at the fingertip centres, z along the pad normal (the side the digit curls
        # towards), x along the digit. Fingers: pad normal = link x; thumb: pad normal = link -y.
        finger_pad = (0.0, 0.0, ALLEGRO_FINGER_LINKS[3], math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0)
        thumb_pad = (0.0, 0.0, ALLEGRO_THUMB_LINKS[2], 0.5, -0.5, 0.5, 0.5)
        zones, zone_bodies, zone_boxes = zone_layout(self.spec.name, self.spec.touch_zones, self.bodies)
        return RobotLayout(
            name=self.spec.name,
            joint_names=tuple(self.names),
            coord_indices=coord,
            dof_indices=dof,
            lower=low,
            upper=up,
            default_q=default_q,
            sensor_names=("index_tip", "middle_tip", "ring_tip", "thumb_tip"),
            sensor_bodies=np.asarray(self.tips) - self.body_start,
            sensor_offsets=np.asarray([finger_pad] * 3 + [thumb_pad]),
            zone_names=zones,
            zone_bodies=zone_bodies,
            zone_boxes=zone_boxes,
        )


def add_hand(builder: newton.ModelBuilder, spec: HandSpec) -> RobotLayout:
    """Add the procedural hand to one world's ``builder``."""
    hand = _HandBuilder(builder, spec)
    palm = hand.wrist_and_palm()
    for name, y in zip(("index", "middle", "ring"), _FINGER_Y, strict=True):
        hand.finger(palm, name, y)
    hand.thumb(palm)
    return hand.layout()
