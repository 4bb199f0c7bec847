"""Robots: the procedural Allegro-like hand on a 6-DoF wrist, and user robots from URDF/MJCF files.

A robot is added to one world's :class:`newton.ModelBuilder`; what the rest of the backend needs
to know about it afterwards (which joint coordinates are actuated, their limits, which links carry
touch sensors and where the sensor frame sits on each) is returned as a :class:`RobotLayout`.
"""

from __future__ import annotations

import importlib.util
import math
import os
import re
import tomllib
import warnings
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import newton
import numpy as np
import warp as wp

__all__ = [
    "ALLEGRO_FINGER_LIMITS",
    "ALLEGRO_THUMB_LIMITS",
    "TIP_RADIUS",
    "FileRobotSpec",
    "HandSpec",
    "RobotLayout",
    "RobotSpec",
    "add_robot",
    "load_robot",
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


@dataclass(frozen=True)
class RobotLayout:
    """What the backend needs to know about a robot once it is in a world's builder.

    Indices are local to one world: world ``w``'s copy is offset by ``w`` times the per-world count.
    """

    name: str
    joint_names: tuple[str, ...]
    """Actuated joints, shape (D,)."""
    coord_indices: np.ndarray
    """Index of each actuated joint in a world's ``joint_q``, shape (D,), int."""
    lower: np.ndarray
    """Lower joint limits, shape (D,) [rad or m]."""
    upper: np.ndarray
    """Upper joint limits, shape (D,) [rad or m]."""
    default_q: np.ndarray
    """Joint positions the robot starts in, shape (D,) [rad or m]."""
    sensor_names: tuple[str, ...]
    """Touch sensor names, shape (L,)."""
    sensor_bodies: np.ndarray
    """Body index of the link carrying each sensor, shape (L,), int."""
    sensor_offsets: np.ndarray
    """Sensor frame in its link's frame, shape (L, 7): position [m] then quaternion (x, y, z, w)."""
    carries_on_palm: bool = False
    """The hand carries objects on a palm that has no touch sensor (see :class:`FileRobotSpec`)."""

    @property
    def dof_count(self) -> int:
        return len(self.joint_names)

    @property
    def sensor_count(self) -> int:
        return len(self.sensor_names)


@dataclass(frozen=True)
class HandSpec:
    """The procedural Allegro-like hand on a 6-DoF position-controlled wrist.

    The wrist stands in for the arm: one joint of six axes, sliding along world x, y, z, then
    turning by yaw about world z, pitch about the turned y and roll about the palm's normal, so
    demos can reach, pick and place. With all wrist angles at zero the palm faces down (world -z)
    and the fingers point along world +x. Fingers flex towards the palm's face; the
    thumb's first joint swings it from beside the palm to in front of it, so it opposes the fingers.
    """

    name: str = "allegro"
    wrist_ke: float = 2.0e4
    """Wrist position gain [N/m for the slides, N m/rad for the hinges]."""
    wrist_kd: float = 4.0e2
    finger_ke: float = 3.0
    """Finger position gain [N m/rad]; the real hand's PD gains are of this order."""
    finger_kd: float = 0.1
    finger_effort: float = 0.7
    """Finger torque limit [N m] (the Allegro's motors give ~0.7 N m)."""
    armature: float = 0.002
    """Rotor inertia added to every finger joint [kg m^2]; keeps light links stable."""
    palm_mass: float = 0.4
    gravity_compensation: bool = True
    """Cancel gravity on the robot's links, as the arm's and hand's controllers do."""
    default_q: tuple[float, ...] = field(default=())
    """Start joints (D=22); empty means wrist at 0.3 m height and an open hand."""


@dataclass(frozen=True)
class FileRobotSpec:
    """A user's robot from a local URDF or MJCF file.

    ``joints`` names the actuated joints in control order; ``sensor_links`` the links that carry
    touch sensors, each with a sensor-frame offset (position [m] and quaternion x, y, z, w).
    """

    name: str
    path: str
    joints: tuple[str, ...]
    sensor_links: tuple[str, ...]
    sensor_offsets: tuple[tuple[float, ...], ...] = ()
    ke: float | tuple[float, ...] = 3.0
    """Position gain of each joint's controller [N m/rad or N/m]: one value, or one per joint."""
    kd: float | tuple[float, ...] = 0.1
    """Damping gain [N m s/rad or N s/m]: one value, or one per joint."""
    effort: float | tuple[float, ...] = 1.0
    """Torque or force limit [N m or N]: one value, or one per joint."""
    floating: bool = False
    base: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    """Pose of the robot's root in the world: position [m], quaternion (x, y, z, w)."""
    default_q: tuple[float, ...] = ()
    carries_on_palm: bool = False
    """The hand carries objects on its palm, which has no touch sensor: fingertips that feel
    nothing then do not say the object fell, so a lost track is re-seeded where the object was,
    not on the table below it."""
    package_dirs: tuple[str, ...] = ()
    """Folders that hold the packages ``package://NAME/...`` mesh paths name (each the parent of a
    NAME folder); the URDF's own package folder is found without it."""


RobotSpec = HandSpec | FileRobotSpec


def add_robot(builder: newton.ModelBuilder, spec: RobotSpec) -> RobotLayout:
    """Add ``spec`` to one world's ``builder`` and describe where its parts landed."""
    if isinstance(spec, HandSpec):
        return _add_hand(builder, spec)
    if isinstance(spec, FileRobotSpec):
        return _add_file_robot(builder, spec)
    raise ValueError(f"robot spec: expected HandSpec or FileRobotSpec, got {type(spec).__name__}")


def _quat_axis_angle(axis: tuple[float, float, float], angle: float) -> wp.quat:
    return wp.quat_from_axis_angle(wp.vec3(*axis), angle)


def _add_hand(builder: newton.ModelBuilder, spec: HandSpec) -> RobotLayout:
    body_start = builder.body_count
    gravcomp = {"mujoco:gravcomp": 1.0} if spec.gravity_compensation else None
    # Hand shapes never collide with each other (collision group -1 on every shape): the fingers
    # are kept apart by their joint limits, and self contacts would only slow the solver down.
    shape_cfg = newton.ModelBuilder.ShapeConfig(density=0.0, collision_group=-1, mu=1.0)

    names: list[str] = []
    lower: list[float] = []
    upper: list[float] = []
    joints: list[int] = []

    def link(mass: float, inertia_diag: float, label: str) -> int:
        inertia = wp.mat33(inertia_diag, 0.0, 0.0, 0.0, inertia_diag, 0.0, 0.0, 0.0, inertia_diag)
        return builder.add_link(mass=mass, inertia=inertia, label=label, custom_attributes=gravcomp)

    # (stiffness, damping, effort limit, armature) of the wrist's and the fingers' position drives
    wrist = (spec.wrist_ke, spec.wrist_kd, 1e3, 0.01)
    finger = (spec.finger_ke, spec.finger_kd, spec.finger_effort, spec.armature)

    def joint(kind: str, parent: int, child: int, axis, lim, name, drive, parent_xform=None):
        ke, kd, effort, armature = drive
        add = builder.add_joint_prismatic if kind == "slide" else builder.add_joint_revolute
        j = add(
            parent,
            child,
            parent_xform=parent_xform or wp.transform_identity(),
            axis=wp.vec3(*axis),
            limit_lower=lim[0],
            limit_upper=lim[1],
            target_ke=ke,
            target_kd=kd,
            effort_limit=effort,
            armature=armature,
            actuator_mode=newton.JointTargetMode.POSITION,
            label=name,
        )
        joints.append(j)
        names.append(name)
        lower.append(lim[0])
        upper.append(lim[1])
        return j

    # Wrist: slides along world x, y, z, then yaw, pitch, roll, as one joint of six axes. It
    # stands in for an arm and has no links of its own: a chain of six single-axis joints moves
    # the same, but is five levels deeper, and the solver's passes over the tree launch once per
    # level and substep (4-5 % of a frame on an H100).
    # The palm frame: x = palm normal (towards the face), z = along the fingers. Turning it by
    # +90 deg about y makes the palm face world -z with the fingers along world +x.
    to_palm = _quat_axis_angle((0, 1, 0), math.pi / 2)
    palm = link(spec.palm_mass, 1e-3, "palm")
    ke, kd, effort, armature = wrist

    def axis_dof(axis: tuple[float, float, float], lim: tuple[float, float]) -> newton.ModelBuilder.JointDofConfig:
        return newton.ModelBuilder.JointDofConfig(
            axis=wp.vec3(*axis), limit_lower=lim[0], limit_upper=lim[1], target_ke=ke, target_kd=kd,
            effort_limit=effort, armature=armature, actuator_mode=newton.JointTargetMode.POSITION,
        )  # fmt: skip

    # The roll turns about the palm frame's x, which is world -z before the palm's turn.
    axes = ((1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, 1), (0, 1, 0), (0, 0, -1))
    dofs = [axis_dof(a, lim) for a, lim in zip(axes, _WRIST_LIMITS, strict=True)]
    inverse_turn = wp.transform(wp.vec3(), wp.quat_inverse(to_palm))
    wrist_joint = builder.add_joint_d6(
        -1, palm, linear_axes=dofs[:3], angular_axes=dofs[3:], child_xform=inverse_turn, label="wrist"
    )
    joints.append(wrist_joint)
    names.extend(_WRIST_NAMES)
    lower.extend(lim[0] for lim in _WRIST_LIMITS)
    upper.extend(lim[1] for lim in _WRIST_LIMITS)
    hx, hy, hz = _PALM_HALF
    builder.add_shape_box(palm, hx=hx, hy=hy, hz=hz, cfg=shape_cfg, label="palm")

    tips: list[int] = []

    def capsule_link(length: float, mass: float, label: str) -> int:
        body = link(mass, mass * length * length / 12.0 + 1e-6, label)
        builder.add_shape_capsule(
            body,
            xform=wp.transform(wp.vec3(0.0, 0.0, 0.5 * length), wp.quat_identity()),
            radius=_LINK_RADIUS,
            half_height=max(0.5 * length - _LINK_RADIUS, 1e-3),
            cfg=shape_cfg,
            label=label,
        )
        return body

    def distal_link(parent_len: float, mass: float, label: str) -> int:
        body = capsule_link(parent_len, mass, label)
        builder.add_shape_sphere(
            body,
            xform=wp.transform(wp.vec3(0.0, 0.0, parent_len), wp.quat_identity()),
            radius=TIP_RADIUS,
            cfg=shape_cfg,
            label=f"{label}_tip",
        )
        return body

    for _f, (fname, y) in enumerate(zip(("index", "middle", "ring"), _FINGER_Y, strict=True)):
        l0, l1, l2, l3 = ALLEGRO_FINGER_LINKS
        m0, m1, m2, m3 = ALLEGRO_FINGER_MASSES
        lim = ALLEGRO_FINGER_LIMITS
        b0 = capsule_link(l0, m0, f"{fname}_link0")
        joint("hinge", palm, b0, (1, 0, 0), lim[0], f"{fname}_0", finger,
              parent_xform=wp.transform(wp.vec3(0.0, y, hz), wp.quat_identity()))  # fmt: skip
        b1 = capsule_link(l1, m1, f"{fname}_link1")
        joint("hinge", b0, b1, (0, 1, 0), lim[1], f"{fname}_1", finger,
              parent_xform=wp.transform(wp.vec3(0.0, 0.0, l0), wp.quat_identity()))  # fmt: skip
        b2 = capsule_link(l2, m2, f"{fname}_link2")
        joint("hinge", b1, b2, (0, 1, 0), lim[2], f"{fname}_2", finger,
              parent_xform=wp.transform(wp.vec3(0.0, 0.0, l1), wp.quat_identity()))  # fmt: skip
        b3 = distal_link(l3, m3, f"{fname}_link3")
        joint("hinge", b2, b3, (0, 1, 0), lim[3], f"{fname}_3", finger,
              parent_xform=wp.transform(wp.vec3(0.0, 0.0, l2), wp.quat_identity()))  # fmt: skip
        tips.append(b3)

    # Thumb: its base sits on the palm's face near the wrist, on the index side. Joint 12 turns it
    # about the palm's long axis from pointing sideways (+y) to pointing out of the face (+x);
    # joint 13 twists it about its own axis; joints 14, 15 curl it towards the fingers (+z).
    t_lim = ALLEGRO_THUMB_LIMITS
    t1, t2, t3 = ALLEGRO_THUMB_LINKS
    b12 = link(0.0176, 1e-5, "thumb_link0")
    joint("hinge", palm, b12, (0, 0, -1), t_lim[0], "thumb_0", finger,
          parent_xform=wp.transform(wp.vec3(hx, 0.02, -0.035), wp.quat_identity()))  # fmt: skip
    builder.add_shape_sphere(b12, radius=_LINK_RADIUS, cfg=shape_cfg, label="thumb_link0")
    # Links below run along local +y (the thumb's axis before joint 12 turns it).
    to_y = _quat_axis_angle((1, 0, 0), -math.pi / 2)  # maps local +z onto +y
    b13 = capsule_link(t1, 0.0119, "thumb_link1")
    joint("hinge", b12, b13, (0, 0, 1), t_lim[1], "thumb_1", finger,
          parent_xform=wp.transform(wp.vec3(0.0, 0.0, 0.0), to_y))  # fmt: skip
    b14 = capsule_link(t2, 0.038, "thumb_link2")
    # After the to_y turn the link frame's x is still the palm normal; turning about it carries
    # the thumb's axis (local z, the palm's +y) towards the palm's +z, the fingers.
    joint("hinge", b13, b14, (1, 0, 0), t_lim[2], "thumb_2", finger,
          parent_xform=wp.transform(wp.vec3(0.0, 0.0, t1), wp.quat_identity()))  # fmt: skip
    b15 = distal_link(t3, 0.0388, "thumb_link3")
    joint("hinge", b14, b15, (1, 0, 0), t_lim[3], "thumb_3", finger,
          parent_xform=wp.transform(wp.vec3(0.0, 0.0, t2), wp.quat_identity()))  # fmt: skip
    tips.append(b15)

    builder.add_articulation(joints, label=spec.name)
    coord, _ = _joint_coord_dof(builder, joints)
    low, up = np.asarray(lower), np.asarray(upper)
    if spec.default_q:
        default_q = np.asarray(spec.default_q, dtype=np.float64)
    else:
        default_q = np.clip(np.zeros(len(names)), low, up)
        default_q[2] = 0.3
        default_q[6 + 12] = 0.263
    # Sensor frames at the fingertip centres, z along the pad normal (the side the digit curls
    # towards), x along the digit. Fingers: pad normal = link x; thumb: pad normal = link -y.
    finger_pad = (0.0, 0.0, ALLEGRO_FINGER_LINKS[3], math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0)
    thumb_pad = (0.0, 0.0, ALLEGRO_THUMB_LINKS[2], 0.5, -0.5, 0.5, 0.5)
    return RobotLayout(
        name=spec.name,
        joint_names=tuple(names),
        coord_indices=coord,
        lower=low,
        upper=up,
        default_q=default_q,
        sensor_names=("index_tip", "middle_tip", "ring_tip", "thumb_tip"),
        sensor_bodies=np.asarray(tips) - body_start,
        sensor_offsets=np.asarray([finger_pad] * 3 + [thumb_pad]),
    )


def _joint_coord_dof(builder: newton.ModelBuilder, joints: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Coordinate and dof index of each degree of freedom of ``joints`` (hinges, slides, D6s)."""
    n = [sum(builder.joint_dof_dim[j]) for j in joints]
    coord = np.concatenate([builder.joint_q_start[j] + np.arange(k) for j, k in zip(joints, n, strict=True)])
    dof = np.concatenate([builder.joint_qd_start[j] + np.arange(k) for j, k in zip(joints, n, strict=True)])
    return coord.astype(np.int64), dof.astype(np.int64)


_PYTHON_URI = re.compile(r"python://([A-Za-z_][\w.]*)/")


def _python_package_path(uri: str) -> str:
    """``python://PACKAGE/rel/path`` as a path inside the installed Python package (found without
    importing it); any other path unchanged. This is how robot models shipped in a package from
    PyPI are named, the way ``package://`` names a ROS package."""
    if not uri.startswith("python://"):
        return uri
    return _PYTHON_URI.sub(lambda m: _package_folder(m.group(1), uri), uri, count=1)


def _package_folder(package: str, uri: str) -> str:
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise ValueError(f"'{uri}' names the Python package '{package}', which is not installed")
    return spec.submodule_search_locations[0] + os.sep


def _mjcf_source(spec: FileRobotSpec) -> str:
    """The MJCF to parse: its path, or, where it names files as ``python://PACKAGE/...`` (an
    include or a ``meshdir``), its text with those made absolute (its other paths must then be
    absolute too). Newton's importer resolves only plain paths, and its custom resolvers drop the
    including file's ``meshdir``."""
    text = Path(spec.path).read_text()
    if "python://" not in text:
        return spec.path
    try:
        return _PYTHON_URI.sub(lambda m: _package_folder(m.group(1), m.group(0)), text)
    except ValueError as exc:
        raise ValueError(f"robot '{spec.name}' path: '{spec.path}' {exc}") from None


def _add_file_robot(builder: newton.ModelBuilder, spec: FileRobotSpec) -> RobotLayout:
    spec = replace(spec, path=_python_package_path(spec.path))
    if not os.path.isfile(spec.path):
        raise ValueError(f"robot '{spec.name}' path: no such file '{spec.path}'")
    body_start, joint_start = builder.body_count, builder.joint_count
    ext = os.path.splitext(spec.path)[1].lower()
    if len(spec.base) != 7:
        raise ValueError(f"robot '{spec.name}' base: expected 7 values (x, y, z, qx, qy, qz, qw), got {len(spec.base)}")
    base = wp.transform(wp.vec3(*spec.base[:3]), wp.normalize(wp.quat(*spec.base[3:])))
    packages = {"package_dirs": list(spec.package_dirs)} if spec.package_dirs else {}
    try:
        # The importers warn and carry on when a mesh path does not resolve, dropping the shape:
        # a hand whose fingertips cannot touch anything would "track" on joints alone.
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if ext == ".urdf":
                builder.add_urdf(spec.path, xform=base, floating=spec.floating, **packages)
            elif ext in (".xml", ".mjcf"):
                builder.add_mjcf(_mjcf_source(spec), xform=base, floating=spec.floating)
            else:
                raise ValueError(f"robot '{spec.name}' path: expected .urdf, .xml or .mjcf, got '{ext}'")
    except ValueError:
        raise
    except Exception as exc:  # parsers raise many kinds; the user needs the file and the cause
        raise ValueError(f"robot '{spec.name}' path: cannot load '{spec.path}': {exc}") from exc
    unresolved = [str(w.message) for w in caught if "resolve" in str(w.message).lower()]
    if unresolved:
        raise ValueError(
            f"robot '{spec.name}' path: '{spec.path}' names files that were not found, so their shapes would be "
            f"dropped: {unresolved[0]} (set package_dirs to the folder that holds the package)"
        )

    labels = [builder.joint_label[j] for j in range(joint_start, builder.joint_count)]
    by_name = {_short(lbl): joint_start + i for i, lbl in enumerate(labels)}
    missing = [n for n in spec.joints if n not in by_name]
    if missing:
        raise ValueError(f"robot '{spec.name}' joints: {missing} not in {spec.path} (has {sorted(by_name)})")
    joints = [by_name[n] for n in spec.joints]
    single = (newton.JointType.REVOLUTE, newton.JointType.PRISMATIC)
    for j in joints:
        if builder.joint_type[j] not in single:
            raise ValueError(
                f"robot '{spec.name}' joints: '{builder.joint_label[j]}' is not a revolute or prismatic joint"
            )
    coord, dof = _joint_coord_dof(builder, joints)
    gains = {name: _per_joint(spec, name) for name in ("ke", "kd", "effort")}
    for i, d in enumerate(dof):
        builder.joint_target_ke[d] = gains["ke"][i]
        builder.joint_target_kd[d] = gains["kd"][i]
        builder.joint_effort_limit[d] = gains["effort"][i]
        builder.joint_target_mode[d] = int(newton.JointTargetMode.POSITION)
    lower = np.asarray([builder.joint_limit_lower[d] for d in dof])
    upper = np.asarray([builder.joint_limit_upper[d] for d in dof])

    body_names = {_short(builder.body_label[b]): b for b in range(body_start, builder.body_count)}
    missing = [n for n in spec.sensor_links if n not in body_names]
    if missing:
        raise ValueError(f"robot '{spec.name}' sensor_links: {missing} not in {spec.path} (has {sorted(body_names)})")
    for link in spec.sensor_links:
        shapes = builder.body_shapes.get(body_names[link], [])
        if not any(builder.shape_flags[sh] & newton.ShapeFlags.COLLIDE_SHAPES for sh in shapes):
            raise ValueError(
                f"robot '{spec.name}' sensor_links: '{link}' in '{spec.path}' has no collision shape, so its "
                f"sensor could never touch the object"
            )
    offsets = np.zeros((len(spec.sensor_links), 7))
    offsets[:, 6] = 1.0
    if spec.sensor_offsets:
        off = np.asarray(spec.sensor_offsets, dtype=np.float64)
        if off.shape != offsets.shape:
            raise ValueError(f"robot '{spec.name}' sensor_offsets: expected shape {offsets.shape}, got {off.shape}")
        offsets = off
    default_q = np.asarray(spec.default_q, dtype=np.float64) if spec.default_q else np.clip(0.0, lower, upper)
    if default_q.shape != lower.shape:
        raise ValueError(f"robot '{spec.name}' default_q: expected {lower.shape[0]} values, got {default_q.shape[0]}")
    return RobotLayout(
        name=spec.name,
        joint_names=tuple(spec.joints),
        coord_indices=coord,
        lower=lower,
        upper=upper,
        default_q=default_q,
        sensor_names=tuple(spec.sensor_links),
        sensor_bodies=np.asarray([body_names[n] for n in spec.sensor_links]) - body_start,
        sensor_offsets=offsets,
        carries_on_palm=spec.carries_on_palm,
    )


def _per_joint(spec: FileRobotSpec, name: str) -> np.ndarray:
    """A controller setting of ``spec`` as one value per joint, (D,)."""
    value = np.atleast_1d(np.asarray(getattr(spec, name), dtype=np.float64))
    if value.shape not in ((1,), (len(spec.joints),)):
        raise ValueError(
            f"robot '{spec.name}' {name}: expected one value or {len(spec.joints)} (one per joint), got {value.size}"
        )
    if not (np.isfinite(value).all() and (value >= 0).all()):
        raise ValueError(f"robot '{spec.name}' {name}: expected finite values >= 0, got {value.tolist()}")
    return np.broadcast_to(value, (len(spec.joints),))


def _short(label: str) -> str:
    """Last path element of a Newton label (importers prefix labels with their parents)."""
    return label.rsplit("/", 1)[-1]


def load_robot(path: str | os.PathLike) -> RobotSpec:
    """A robot from a TOML file (see configs/robots/): ``kind = "hand"`` for the procedural hand,
    ``kind = "file"`` for a URDF/MJCF robot whose ``path`` is relative to the TOML file."""
    path = Path(path)
    try:
        table = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"robot config: cannot read '{path}': {exc}") from exc
    kind = table.pop("kind", None)
    cls = {"hand": HandSpec, "file": FileRobotSpec}.get(kind)
    if cls is None:
        raise ValueError(f"robot config '{path}' kind: expected 'hand' or 'file', got {kind!r}")
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ValueError(f"robot config '{path}': unknown keys {unknown} for kind '{kind}' (known: {sorted(known)})")
    if kind == "file":
        if not str(table.get("path", "")).startswith("python://"):
            table["path"] = str(path.parent / table["path"])
        table["package_dirs"] = tuple(str(path.parent / d) for d in table.get("package_dirs", ()))
        table["sensor_offsets"] = tuple(tuple(o) for o in table.get("sensor_offsets", ()))
    table = {k: tuple(v) if isinstance(v, list) else v for k, v in table.items()}
    try:
        return cls(**table)
    except TypeError as exc:
        raise ValueError(f"robot config '{path}': {exc}") from exc
