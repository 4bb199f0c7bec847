"""Simulation backend: K worlds of hand + object per group on Newton, stepped as one graph."""

from .demos import Recording, pinch_lift_twist, record
from .grasp import Grasp, plan_pinch
from .kinematics import Kinematics, SensorFK
from .objects import CATALOG, ObjectSpec, catalog_object, load_catalog, load_mesh_object, make_banana
from .observe import HEALTH_LOST, HEALTH_NAN, HEALTH_OK
from .population import Observation, Population, PopulationConfig, resolve_device
from .robots import FileRobotSpec, HandSpec, RobotLayout, RobotSpec, add_robot, load_robot

__all__ = [
    "CATALOG",
    "HEALTH_LOST",
    "HEALTH_NAN",
    "HEALTH_OK",
    "FileRobotSpec",
    "Grasp",
    "HandSpec",
    "Kinematics",
    "ObjectSpec",
    "Observation",
    "Population",
    "PopulationConfig",
    "Recording",
    "RobotLayout",
    "RobotSpec",
    "SensorFK",
    "add_robot",
    "catalog_object",
    "load_catalog",
    "load_mesh_object",
    "load_robot",
    "make_banana",
    "pinch_lift_twist",
    "plan_pinch",
    "record",
    "resolve_device",
]
