"""What a robot is: its spec as a user writes it (the procedural hand, or a URDF/MJCF file with
its servos and touch sensors), read from a robot config, and its layout once it is in a world."""

from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

import newton
import numpy as np

__all__ = [
    "FileRobotSpec",
    "HandSpec",
    "RobotLayout",
    "RobotSpec",
    "SensorNoise",
    "TouchZone",
    "TrackerDefaults",
    "joint_coord_dof",
    "load_robot",
    "zone_layout",
]


@dataclass(frozen=True)
class TouchZone:
    """A region of a link that reports one scalar normal force, as a touch array's cell, a pressure
    pad or a patch of taxel skin does: a box in the link's frame."""

    name: str
    link: str
    """The link that carries it, by its name in the robot's model."""
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The box's centre in the link's frame [m]."""
    half_extents: tuple[float, float, float] = (0.01, 0.01, 0.01)
    """The box's half extents along the link frame's axes [m]; contacts inside it count."""

    def __post_init__(self) -> None:
        if len(self.center) != 3 or len(self.half_extents) != 3:
            raise ValueError(f"touch zone '{self.name}': expected 3 values for center and half_extents")
        if not all(h > 0 for h in self.half_extents):
            raise ValueError(f"touch zone '{self.name}' half_extents: expected > 0 m, got {list(self.half_extents)}")


def zone_layout(
    robot: str, zones: tuple[TouchZone, ...], bodies: dict[str, int]
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """The touch zones' names, their links' body indices (Z,) from ``bodies`` (link name -> index
    local to the world), and their boxes (Z, 6): centre then half extents [m]; a ValueError names a
    zone whose link the robot lacks."""
    missing = [(z.name, z.link) for z in zones if z.link not in bodies]
    if missing:
        raise ValueError(f"robot '{robot}' touch_zones: links {missing} not in the robot (has {sorted(bodies)})")
    names = tuple(z.name for z in zones)
    if len(set(names)) != len(names):
        raise ValueError(f"robot '{robot}' touch_zones: names repeat: {names}")
    boxes = np.array([[*z.center, *z.half_extents] for z in zones], np.float32).reshape(len(zones), 6)
    return names, np.array([bodies[z.link] for z in zones], np.int64), boxes


@dataclass(frozen=True)
class RobotLayout:
    """What the backend needs to know about a robot once it is in a world's builder.

    Indices are local to one world: world ``w``'s copy is offset by ``w`` times the per-world count.
    """

    name: str
    joint_names: tuple[str, ...]
    """The robot's joints, commanded and measured, in the order its frames carry them, shape (D,)."""
    coord_indices: np.ndarray
    """Index of each actuated joint in a world's ``joint_q``, shape (D,), int."""
    dof_indices: np.ndarray
    """Index of each actuated joint in a world's ``joint_qd`` and per-DOF settings (its servo's
    gains and effort limit), shape (D,), int."""
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
    zone_names: tuple[str, ...] = ()
    """Touch zone names, shape (Z,)."""
    zone_bodies: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """Body index of the link carrying each zone, shape (Z,), int."""
    zone_boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), np.float32))
    """Each zone's box in its link's frame, shape (Z, 6): centre then half extents [m]."""
    options: dict = field(default_factory=dict)
    """The physics options the robot's file runs under, by PopulationConfig's names ("cone",
    "impratio", "integrator", "collision"), and its "timestep" [s]: an MJCF's ``<option>``, MuJoCo's defaults
    where it says none; empty for a URDF and the procedural hand (:func:`.build.resolve_physics`
    states the precedence; the timestep is said where the worlds' differs, :func:`.build.say_timestep`)."""
    actuated: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    """Which joints the robot drives, shape (D,) bool (empty: all). A joint it does not drive (a
    distal joint a tendon couples to the middle one) is measured and scored; its command is not used."""

    def __post_init__(self) -> None:
        if self.actuated.size == 0:
            object.__setattr__(self, "actuated", np.ones(len(self.joint_names), bool))

    @property
    def dof_count(self) -> int:
        return len(self.joint_names)

    @property
    def sensor_count(self) -> int:
        return len(self.sensor_names)

    @property
    def zone_count(self) -> int:
        return len(self.zone_names)


CONES = ("pyramidal", "elliptic")
"""MuJoCo's friction cones."""


@dataclass(frozen=True, kw_only=True)
class ContactModel:
    """The contact model a robot's model was written for, which its worlds run unless the service's
    physics or a benchmark's ``--set`` name another (:func:`.build.resolve_physics`)."""

    cone: str | None = None
    """The friction cone, "pyramidal" or "elliptic" (an MJCF's ``<option cone>``, MuJoCo's default
    pyramidal where it says none); None: the service's default (elliptic)."""
    impratio: float | None = None
    """The frictional-to-normal impedance ratio (an MJCF's ``<option impratio>``, MuJoCo's default
    1); None: the service's default (10)."""
    collision: str | None = None
    """Who finds the contacts, "mujoco" or "newton" (:attr:`.PopulationConfig.collision`); None:
    MuJoCo's own for a robot from an MJCF, Newton's for the rest."""

    def __post_init__(self) -> None:
        name = getattr(self, "name", "")
        if self.cone is not None and self.cone not in CONES:
            raise ValueError(f"robot '{name}' cone: expected one of {CONES}, got {self.cone!r}")
        if self.collision not in (None, "mujoco", "newton"):
            raise ValueError(f"robot '{name}' collision: expected 'mujoco' or 'newton', got {self.collision!r}")
        if self.impratio is not None and not self.impratio > 0:
            raise ValueError(f"robot '{name}' impratio: expected > 0, got {self.impratio}")
        super().__post_init__()


@dataclass(frozen=True, kw_only=True)
class SensorNoise:
    """The noise of the robot's sensing as its maker or a user measured it, a standard deviation per
    reading: the tracker's updates never move the worlds on cost differences this noise could make
    (:func:`inhand_tracker.service.tracker.evidence.separation`). 0: the noise the worlds' own
    frame-to-frame scatter shows."""

    joint_noise: float = 0.0
    """Measured joint positions [rad or m]."""
    force_noise: float = 0.0
    """Each fingertip force's magnitude [N]."""
    touch_noise: float = 0.0
    """Each touch zone's normal force [N]. A zone's force difference between a world and the robot
    within twice this ranks no world above another."""
    touch_deadband: float = 0.0
    """The normal force [N] under which a touch zone reads 0. The worlds' zones read as the robot's
    do: a world that presses a zone lightly is not told apart from one that does not touch it."""

    def __post_init__(self) -> None:
        for name in ("joint_noise", "force_noise", "touch_noise", "touch_deadband"):
            value = getattr(self, name)
            if not 0.0 <= value < 1e3:
                raise ValueError(f"robot '{getattr(self, 'name', '')}' {name}: expected >= 0, got {value}")


@dataclass(frozen=True, kw_only=True)
class TrackerDefaults:
    """The tracker settings a robot's sessions start from, where its sensing calls for other than the
    defaults (a palm felt through two coarse zones, say): the config's ``[tracker]`` table, by the
    settings' dotted names (:mod:`inhand_tracker.service.tracker.settings`). A session's overrides
    and ``bench accuracy --set`` change them; the service checks the names when it loads the robot."""

    tracker: tuple[tuple[str, bool | int | float | str], ...] | None = None
    """(dotted name, value) pairs, e.g. ``("optimizer.open_loop_ratio", 1.5)``; () for an empty table
    (the defaults, chosen), None where the config gives none (the defaults, not checked against the
    robot: the service says so once for a robot that carries objects on its palm)."""


@dataclass(frozen=True)
class HandSpec(ContactModel, SensorNoise, TrackerDefaults):
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
    touch_zones: tuple[TouchZone, ...] = ()
    """Regions of the links that sense a normal force (``touch`` in a frame); none by default."""
    servos: tuple[tuple[str, tuple[float, ...]], ...] = ()
    """Servo settings per actuated joint that replace the config's, as a calibration fitted them:
    ("ke" | "kd" | "effort", one value per joint); the ``[servos]`` table of a config."""


@dataclass(frozen=True)
class FileRobotSpec(ContactModel, SensorNoise, TrackerDefaults):
    """A user's robot from a local URDF or MJCF file.

    ``joints`` names the actuated joints in control order; ``sensor_links`` the links that carry
    touch sensors, each with a sensor-frame offset (position [m] and quaternion x, y, z, w).
    """

    name: str
    path: str
    joints: tuple[str, ...]
    sensor_links: tuple[str, ...]
    sensor_offsets: tuple[tuple[float, ...], ...] = ()
    ke: float | tuple[float, ...] | None = None
    """Position gain of each joint's controller [N m/rad or N/m]: one value, or one per joint.
    None: the file's actuators' where it declares them, else 3."""
    kd: float | tuple[float, ...] | None = None
    """Damping gain [N m s/rad or N s/m]: one value, or one per joint. None: the file's, else 0.1."""
    effort: float | tuple[float, ...] | None = None
    """Torque or force limit [N m or N]: one value, or one per joint. None: the file's actuators'
    force ranges, else 1."""
    floating: bool = False
    base: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    """Pose of the robot's root in the world: position [m], quaternion (x, y, z, w)."""
    default_q: tuple[float, ...] = ()
    carries_on_palm: bool = False
    """The hand carries objects on its palm, which has no touch sensor: fingertips that feel
    nothing then do not say the object fell, so a lost track is re-seeded where the object was,
    not on the table below it."""
    touch_zones: tuple[TouchZone, ...] = ()
    """Regions of the links that sense a normal force (``touch`` in a frame): ``[[touch_zones]]``
    tables in the robot config, each with a name, a link, a center and half_extents."""
    servos: tuple[tuple[str, tuple[float, ...]], ...] = ()
    """Servo settings per actuated joint that replace the config's, as a calibration fitted them:
    ("ke" | "kd" | "effort", one value per joint); the ``[servos]`` table of a config."""
    touch_sites: str = ""
    """A regular expression: the MJCF's sites whose names match it become touch zones too (their
    box, or a sphere's bounding box, on the link that carries them), as a model that declares
    MuJoCo touch sensors on sites describes its touch array; empty for none."""
    package_dirs: tuple[str, ...] = ()
    """Folders that hold the packages ``package://NAME/...`` mesh paths name (each the parent of a
    NAME folder); the URDF's own package folder is found without it."""


RobotSpec = HandSpec | FileRobotSpec


SERVO_ARRAYS = {
    "ke": "joint_target_ke",
    "kd": "joint_target_kd",
    "effort": "joint_effort_limit",
    "damping": "joint_damping",
    "armature": "joint_armature",
    "friction": "joint_friction",
}
"""Each joint setting a config's ``[servos]`` may give per joint, and the builder's and model's
per-DOF array that holds it: the position servo's gain [N m/rad or N/m], damping [N m s/rad or
N s/m] and force limit [N m or N]; the joint's own damping (a robot file's ``damping``, on top of
the servo's), armature [kg m^2 or kg] and dry friction (``frictionloss``) [N m or N]."""


def _read_config(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    """A robot config's table, its file paths made absolute; an overlay (``extends = "BASE.toml"``,
    relative to it) is its base's table with the overlay's keys replacing the base's."""
    try:
        table = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"robot config: cannot read '{path}': {exc}") from exc
    if table.get("kind") == "file" or "path" in table:
        if "path" in table and not str(table["path"]).startswith("python://"):
            table["path"] = str(path.parent / table["path"])
        if "package_dirs" in table:
            table["package_dirs"] = [str(path.parent / d) for d in table["package_dirs"]]
    base = table.pop("extends", None)
    if base is None:
        return table
    base_path = (path.parent / base).resolve()
    if base_path in seen:
        raise ValueError(f"robot config '{path}' extends: '{base}' extends itself in a loop")
    return _read_config(base_path, (*seen, base_path)) | table


def load_robot(path: str | os.PathLike) -> RobotSpec:
    """A robot from a TOML file (see configs/robots/): ``kind = "hand"`` for the procedural hand,
    ``kind = "file"`` for a URDF/MJCF robot whose ``path`` is relative to the TOML file; an overlay
    (``extends = "BASE.toml"``, as a calibration writes) changes its base's keys."""
    path = Path(path)
    table = _read_config(path)
    kind = table.pop("kind", None)
    cls = {"hand": HandSpec, "file": FileRobotSpec}.get(kind)
    if cls is None:
        raise ValueError(f"robot config '{path}' kind: expected 'hand' or 'file', got {kind!r}")
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ValueError(f"robot config '{path}': unknown keys {unknown} for kind '{kind}' (known: {sorted(known)})")
    if kind == "file":
        table["package_dirs"] = tuple(table.get("package_dirs", ()))
        table["sensor_offsets"] = tuple(tuple(o) for o in table.get("sensor_offsets", ()))
    servos = table.pop("servos", {})
    if not isinstance(servos, dict) or sorted(set(servos) - set(SERVO_ARRAYS)):
        raise ValueError(f"robot config '{path}' servos: expected a table of {list(SERVO_ARRAYS)}, got {servos!r}")
    table["servos"] = tuple((k, tuple(float(x) for x in v)) for k, v in servos.items())
    given = table.pop("tracker", None)
    table["tracker"] = None if given is None else _dotted(path, given)
    try:
        zones = tuple(TouchZone(**{k: tuple(v) if isinstance(v, list) else v for k, v in z.items()})
                      for z in table.pop("touch_zones", ()))  # fmt: skip
    except (TypeError, ValueError) as exc:
        raise ValueError(f"robot config '{path}' touch_zones: {exc}") from None
    table = {k: tuple(v) if isinstance(v, list) else v for k, v in table.items()} | {"touch_zones": zones}
    try:
        return cls(**table)
    except TypeError as exc:
        raise ValueError(f"robot config '{path}': {exc}") from exc


def _dotted(path: Path, table: object, prefix: str = "") -> tuple[tuple[str, bool | int | float | str], ...]:
    """A ``[tracker]`` table's values by dotted name: ``[tracker.optimizer] open_loop_ratio = 1.5``
    is ``("optimizer.open_loop_ratio", 1.5)``."""
    if not isinstance(table, dict):
        raise ValueError(f"robot config '{path}' tracker: expected a table of settings, got {table!r}")
    out: list[tuple[str, bool | int | float | str]] = []
    for key, value in table.items():
        name = f"{prefix}.{key}" if prefix else key
        if isinstance(value, dict):
            out += _dotted(path, value, name)
        elif isinstance(value, bool | int | float | str):
            out.append((name, value))
        else:
            raise ValueError(f"robot config '{path}' tracker.{name}: expected a number, flag or name, got {value!r}")
    return tuple(out)


def joint_coord_dof(builder: newton.ModelBuilder, joints: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Coordinate and dof index of each degree of freedom of ``joints`` (hinges, slides, D6s)."""
    n = [sum(builder.joint_dof_dim[j]) for j in joints]
    coord = np.concatenate([builder.joint_q_start[j] + np.arange(k) for j, k in zip(joints, n, strict=True)])
    dof = np.concatenate([builder.joint_qd_start[j] + np.arange(k) for j, k in zip(joints, n, strict=True)])
    return coord.astype(np.int64), dof.astype(np.int64)
