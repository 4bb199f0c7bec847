"""Robots: the procedural Allegro-like hand on a 6-DoF wrist (:mod:`.hand`), and user robots
from URDF/MJCF files (:mod:`.robot_files`).

A robot is added to one world's :class:`newton.ModelBuilder`; what the rest of the backend needs
to know about it afterwards (which joint coordinates are actuated, their limits, which links carry
touch sensors and where the sensor frame sits on each) is returned as a :class:`RobotLayout`.
"""

from __future__ import annotations

import math

import newton

from .hand import ALLEGRO_FINGER_LIMITS, ALLEGRO_THUMB_LIMITS, TIP_RADIUS, add_hand
from .robot_files import add_file_robot
from .robot_specs import SERVO_ARRAYS, FileRobotSpec, HandSpec, RobotLayout, RobotSpec, TouchZone, load_robot

__all__ = [
    "ALLEGRO_FINGER_LIMITS",
    "ALLEGRO_THUMB_LIMITS",
    "SERVO_ARRAYS",
    "TIP_RADIUS",
    "FileRobotSpec",
    "HandSpec",
    "RobotLayout",
    "RobotSpec",
    "TouchZone",
    "add_robot",
    "load_robot",
]


def add_robot(builder: newton.ModelBuilder, spec: RobotSpec) -> RobotLayout:
    """Add ``spec`` to one world's ``builder`` and describe where its parts landed."""
    if isinstance(spec, HandSpec):
        layout = add_hand(builder, spec)
    elif isinstance(spec, FileRobotSpec):
        layout = add_file_robot(builder, spec)
    else:
        raise ValueError(f"robot spec: expected HandSpec or FileRobotSpec, got {type(spec).__name__}")
    _set_servos(builder, spec, layout)
    return layout


def _set_servos(builder: newton.ModelBuilder, spec: RobotSpec, layout: RobotLayout) -> None:
    """The spec's per-joint servo settings (a calibration's) in place of the config's."""
    for name, values in spec.servos:
        if name not in SERVO_ARRAYS:
            raise ValueError(f"robot '{spec.name}' servos: unknown setting '{name}' (known: {sorted(SERVO_ARRAYS)})")
        if len(values) != layout.dof_count or not all(math.isfinite(v) and v >= 0 for v in values):
            raise ValueError(
                f"robot '{spec.name}' servos {name}: expected {layout.dof_count} finite values >= 0 (one per joint), "
                f"got {list(values)}"
            )
        target = getattr(builder, SERVO_ARRAYS[name])
        for d, v in zip(layout.dof_indices, values, strict=True):
            target[int(d)] = v
