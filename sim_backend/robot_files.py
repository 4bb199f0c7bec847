"""A user's robot from a URDF or MJCF file: imported into a world's builder with the file's own
actuation (an MJCF's actuators: their gains, damping and force ranges; a joint it leaves
unactuated stays passive, held by its tendons, limits and springs), or, for a file without
actuators, a position servo per listed joint from the spec; its touch sensors found on their
links. Paths may name files in an installed Python package as ``python://PACKAGE/...``, the way
``package://`` names a ROS package."""

from __future__ import annotations

import importlib.util
import os
import re
import warnings
from dataclasses import replace
from pathlib import Path
from xml.etree import ElementTree

import newton
import numpy as np
import warp as wp

from .robot_specs import FileRobotSpec, RobotLayout, TouchZone, joint_coord_dof, zone_layout

__all__ = ["add_file_robot", "python_package_path"]

_PYTHON_URI = re.compile(r"python://([A-Za-z_][\w.]*)/")


def python_package_path(uri: str) -> str:
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


def add_file_robot(builder: newton.ModelBuilder, spec: FileRobotSpec) -> RobotLayout:
    spec = replace(spec, path=python_package_path(spec.path))
    if not os.path.isfile(spec.path):
        raise ValueError(f"robot '{spec.name}' path: no such file '{spec.path}'")
    body_start, joint_start, shape_start = builder.body_count, builder.joint_count, builder.shape_count
    pair_start = _pair_count(builder)
    ext = os.path.splitext(spec.path)[1].lower()
    if len(spec.base) != 7:
        raise ValueError(f"robot '{spec.name}' base: expected 7 values (x, y, z, qx, qy, qz, qw), got {len(spec.base)}")
    _import(builder, spec, ext)
    _collide_pairs(builder, shape_start, pair_start)

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
    coord, dof = joint_coord_dof(builder, joints)
    actuated = _actuate(builder, spec, dof)
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
    local = {name: b - body_start for name, b in body_names.items()}
    sites = _site_zones(builder, spec, body_start) if spec.touch_sites else ()
    zones, zone_bodies, zone_boxes = zone_layout(spec.name, spec.touch_zones + sites, local)
    default_q = np.asarray(spec.default_q, dtype=np.float64) if spec.default_q else np.clip(0.0, lower, upper)
    if default_q.shape != lower.shape:
        raise ValueError(f"robot '{spec.name}' default_q: expected {lower.shape[0]} values, got {default_q.shape[0]}")
    return RobotLayout(
        name=spec.name,
        joint_names=tuple(spec.joints),
        coord_indices=coord,
        dof_indices=dof,
        lower=lower,
        upper=upper,
        default_q=default_q,
        sensor_names=tuple(spec.sensor_links),
        sensor_bodies=np.asarray([body_names[n] for n in spec.sensor_links]) - body_start,
        sensor_offsets=offsets,
        carries_on_palm=spec.carries_on_palm,
        actuated=actuated,
        options=_file_options(builder) | _file_timestep(spec.path) if ext in (".xml", ".mjcf") else {},
        zone_names=zones,
        zone_bodies=zone_bodies,
        zone_boxes=zone_boxes,
    )


def _site_zones(builder: newton.ModelBuilder, spec: FileRobotSpec, body_start: int) -> tuple[TouchZone, ...]:
    """The touch zones of the robot's sites whose names match ``spec.touch_sites``, in the file's
    order: each site's box (a sphere's bounding cube) as the axis-aligned box that bounds it in
    its link's frame."""
    try:
        pattern = re.compile(spec.touch_sites)
    except re.error as exc:
        raise ValueError(f"robot '{spec.name}' touch_sites: not a regular expression: {exc}") from None
    zones = []
    for sh in range(builder.shape_count):
        name = _short(builder.shape_label[sh])
        if not (builder.shape_flags[sh] & newton.ShapeFlags.SITE) or builder.shape_body[sh] < body_start:
            continue
        if not pattern.fullmatch(name):
            continue
        kind, scale = builder.shape_type[sh], np.asarray(builder.shape_scale[sh], np.float64)
        if kind == newton.GeoType.SPHERE:
            half = np.full(3, scale[0])
        elif kind == newton.GeoType.BOX:
            half = scale
        else:
            raise ValueError(
                f"robot '{spec.name}' touch_sites: site '{name}' is a {kind.name.lower()}; expected a box or a sphere"
            )
        xform = builder.shape_transform[sh]
        turn = np.abs(np.array(wp.quat_to_matrix(wp.quat(*xform[3:])), np.float64).reshape(3, 3))
        link = _short(builder.body_label[builder.shape_body[sh]])
        zones.append(TouchZone(name, link, tuple(float(c) for c in xform[:3]), tuple(float(h) for h in turn @ half)))
    if not zones:
        raise ValueError(f"robot '{spec.name}' touch_sites: no site of '{spec.path}' matches '{spec.touch_sites}'")
    return tuple(zones)


_DEFAULT_SERVO = {"ke": 3.0, "kd": 0.1, "effort": 1.0}
"""A file without actuators: each listed joint's position servo where the config gives none."""


def _actuate(builder: newton.ModelBuilder, spec: FileRobotSpec, dof: list[int]) -> np.ndarray:
    """Drive the listed joints as the file does, and say which it drives, (D,) bool.

    An MJCF that declares actuators keeps them: each position actuator on a listed joint is its
    servo (the importer's gain and damping, its force range as the effort limit), and a joint the
    file does not drive stays passive, whatever the config says (the Shadow hand's distal joints
    follow their middle ones through tendons). The config's ``ke``, ``kd`` and ``effort``, where it
    gives them, replace the file's on the joints the file drives. A file without actuators (a URDF)
    gets a position servo on every listed joint: the config's settings, else the defaults."""
    mode = np.asarray([builder.joint_target_mode[d] for d in dof])
    from_file = bool((mode != int(newton.JointTargetMode.NONE)).any())
    actuated = mode != int(newton.JointTargetMode.NONE) if from_file else np.ones(len(dof), bool)
    ranges = _actuator_force_ranges(builder) if from_file else {}
    for name in ("ke", "kd", "effort"):
        given = getattr(spec, name)
        if given is None and from_file:
            continue
        values = _per_joint(spec, name, _DEFAULT_SERVO[name] if given is None else given)
        for i, d in enumerate(dof):
            if actuated[i]:
                {"ke": builder.joint_target_ke, "kd": builder.joint_target_kd, "effort": builder.joint_effort_limit}[
                    name
                ][d] = values[i]
    for i, d in enumerate(dof):
        if not actuated[i]:
            builder.joint_target_mode[d] = int(newton.JointTargetMode.NONE)
            builder.joint_target_ke[d] = builder.joint_target_kd[d] = 0.0
        elif not from_file:
            builder.joint_target_mode[d] = int(newton.JointTargetMode.POSITION)
        elif spec.effort is None and d in ranges:
            builder.joint_effort_limit[d] = ranges[d]
    return actuated


_MUJOCO_OPTIONS = {"cone": ("pyramidal", ("pyramidal", "elliptic")), "impratio": (1.0, None),
                   "integrator": ("euler", ("euler", "rk4", "implicit", "implicitfast"))}  # fmt: skip
"""MuJoCo's own defaults for the options a file may state, and the names of their enum values."""


def _file_options(builder: newton.ModelBuilder) -> dict:
    """The options the MJCF states (its ``<option>``, as the importer read it), MuJoCo's defaults
    for the rest: what MuJoCo C runs the file with, its own collision detection included."""
    out = {"collision": "mujoco"}
    for name, (default, names) in _MUJOCO_OPTIONS.items():
        attr = builder.custom_attributes.get(f"mujoco:{name}")
        values = attr.values if attr is not None else {}
        stated = values.get(0) if isinstance(values, dict) else (values[0] if len(values) else None)
        if stated is None:
            out[name] = default
        else:
            out[name] = names[int(stated)] if names else float(stated)
    return out


def _file_timestep(path: str) -> dict:
    """The MJCF's ``<option timestep>`` [s], MuJoCo's 0.002 where it states none. Newton's importer
    does not keep it (the worlds step each frame in substeps), so it is read here to be said."""
    try:
        option = ElementTree.parse(path).getroot().find("option")
    except (ElementTree.ParseError, OSError):
        option = None
    return {"timestep": float(option.get("timestep", 0.002)) if option is not None else 0.002}


def _actuator_force_ranges(builder: newton.ModelBuilder) -> dict[int, float]:
    """The force range of each joint actuator the MJCF gives one, by the DOF it drives [N m or N]:
    the servo's effort limit (the importer keeps it on the actuator only)."""
    attr = builder.custom_attributes
    if "mujoco:actuator_trnid" not in attr:
        return {}
    rows = zip(
        *(attr[f"mujoco:actuator_{k}"].values for k in ("trnid", "trntype", "has_forcerange", "forcerange")),
        strict=True,
    )
    return {int(t[0]): float(max(abs(r[0]), abs(r[1]))) for t, kind, has, r in rows if kind == 0 and has}


def _per_joint(spec: FileRobotSpec, name: str, value) -> np.ndarray:
    """A controller setting ``value`` of ``spec`` as one value per joint, (D,)."""
    value = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if value.shape not in ((1,), (len(spec.joints),)):
        raise ValueError(
            f"robot '{spec.name}' {name}: expected one value or {len(spec.joints)} (one per joint), got {value.size}"
        )
    if not (np.isfinite(value).all() and (value >= 0).all()):
        raise ValueError(f"robot '{spec.name}' {name}: expected finite values >= 0, got {value.tolist()}")
    return np.broadcast_to(value, (len(spec.joints),))


def _pair_count(builder: newton.ModelBuilder) -> int:
    """How many explicit contact pairs (MJCF ``<contact><pair>``) the builder holds."""
    attr = builder.custom_attributes.get("mujoco:pair_geom1")
    return len(attr.values) if attr is not None and isinstance(attr.values, list) else 0


def _collide_pairs(builder: newton.ModelBuilder, shape_start: int, pair_start: int) -> None:
    """Let the shape pairs an MJCF names in ``<contact><pair>`` (from ``pair_start`` on) collide in
    Newton's collision pipeline, which the worlds use: Newton's importer keeps them for MuJoCo's own
    collision only, so a hand whose contype and conaffinity keep its links apart (the Shadow hand's)
    would pass its thumb through its fingers, where the real hand's touch sensors read them pressing
    each other. Each paired shape gets a collision group of its own, which collides with every
    group, and a filter pair for each robot shape it collided with neither before nor by the file's
    pairs. A paired shape also takes the smallest ``condim`` of its pairs (the Shadow hand's are all
    1, frictionless): MuJoCo gives a contact of two shapes of one priority the larger of their
    condims, so two paired shapes touch as their pair says wherever each shape's pairs agree (the
    Shadow hand's do); the object (of higher priority) touches them as before, and any other shape
    by its own condim. Kept as the shapes have them: the pairs' friction and solver settings."""
    attr = lambda name: builder.custom_attributes[name].values  # noqa: E731
    if _pair_count(builder) <= pair_start:
        return
    named = zip(*(attr(f"mujoco:pair_{k}")[pair_start:] for k in ("geom1", "geom2", "condim")), strict=True)
    pairs: set[frozenset[int]] = set()
    condim: dict[int, int] = {}  # each paired shape's smallest pair condim
    for a, b, c in named:
        if a >= shape_start and b >= shape_start:
            pairs.add(frozenset((int(a), int(b))))
            for s in (int(a), int(b)):
                condim[s] = min(condim.get(s, int(c)), int(c))
    paired = sorted(condim)
    for s in paired:
        # Frictionless pairs: fingers that press each other slide, as the file's hand does.
        attr("mujoco:condim")[s] = condim[s]
    shapes = [
        s for s in range(shape_start, builder.shape_count) if builder.shape_flags[s] & newton.ShapeFlags.COLLIDE_SHAPES
    ]
    group = list(builder.shape_collision_group)
    filtered = {frozenset(p) for p in builder.shape_collision_filter_pairs}

    def collided(a: int, b: int) -> bool:
        # Newton's broad phase (broad_phase_common.test_group_pair): group 0 collides with nothing, a
        # positive group with itself and the negatives, a negative one with all but itself.
        ga, gb = group[a], group[b]
        if ga == 0 or gb == 0 or builder.shape_body[a] == builder.shape_body[b] or frozenset((a, b)) in filtered:
            return False
        return (ga == gb or gb < 0) if ga > 0 else ga != gb

    exclude = {frozenset((a, b)) for a in paired for b in shapes if a != b and not collided(a, b)} - pairs
    fresh = min(min(group, default=0), 0) - 1
    for i, s in enumerate(paired):
        builder.shape_collision_group[s] = fresh - i
    for a, b in sorted(tuple(sorted(p)) for p in exclude):
        builder.add_shape_collision_filter_pair(a, b)


def _short(label: str) -> str:
    """Last path element of a Newton label (importers prefix labels with their parents)."""
    return label.rsplit("/", 1)[-1]


def _import(builder: newton.ModelBuilder, spec: FileRobotSpec, ext: str) -> None:
    """Import the robot's file into ``builder`` at its base pose; a ValueError names the file and
    the cause, and a mesh path that does not resolve is one (the importers would drop its shape)."""
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
