"""Simulation backend: K worlds of hand + object per group on Newton, stepped as one graph."""

from .demos import DEMO_KINDS, Demo, Recording, make_demo, record, sensitivity
from .grasp import Grasp, plan_pinch
from .kinematics import Kinematics, SensorFK
from .objects import CATALOG, ObjectSpec, catalog_object, load_catalog, load_mesh_object, make_banana
from .observe import HEALTH_LOST, HEALTH_NAN, HEALTH_OK
from .population import Observation, Population, PopulationConfig, SolverSettings, resolve_device
from .robots import FileRobotSpec, HandSpec, RobotLayout, RobotSpec, add_robot, load_robot

__all__ = [
    "CATALOG",
    "DEMO_KINDS",
    "HEALTH_LOST",
    "HEALTH_NAN",
    "HEALTH_OK",
    "Demo",
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
    "SolverSettings",
    "add_robot",
    "catalog_object",
    "load_catalog",
    "load_mesh_object",
    "load_robot",
    "make_banana",
    "make_demo",
    "plan_pinch",
    "record",
    "resolve_device",
    "sensitivity",
]
