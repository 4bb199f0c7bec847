"""Robots: the procedural Allegro-like hand on a 6-DoF wrist (:mod:`.hand`), and user robots
from URDF/MJCF files (:mod:`.robot_files`).

A robot is added to one world's :class:`newton.ModelBuilder`; what the rest of the backend needs
to know about it afterwards (which joint coordinates are actuated, their limits, which links carry
touch sensors and where the sensor frame sits on each) is returned as a :class:`RobotLayout`.
"""

from __future__ import annotations

import newton

from .hand import ALLEGRO_FINGER_LIMITS, ALLEGRO_THUMB_LIMITS, TIP_RADIUS, add_hand
from .robot_files import add_file_robot
from .robot_specs import FileRobotSpec, HandSpec, RobotLayout, RobotSpec, TouchZone, load_robot

__all__ = [
    "ALLEGRO_FINGER_LIMITS",
    "ALLEGRO_THUMB_LIMITS",
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
        return add_hand(builder, spec)
    if isinstance(spec, FileRobotSpec):
        return add_file_robot(builder, spec)
    raise ValueError(f"robot spec: expected HandSpec or FileRobotSpec, got {type(spec).__name__}")
