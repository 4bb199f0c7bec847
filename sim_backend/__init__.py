"""Simulation backend: K worlds of hand + object per group on Newton, stepped as one graph."""

from .grasp import Grasp, plan_pinch
from .kinematics import Kinematics
from .objects import CATALOG, ObjectSpec, catalog_object, load_catalog, load_mesh_object, make_banana
from .observe import HEALTH_LOST, HEALTH_NAN, HEALTH_OK
from .population import Observation, Population, PopulationConfig, resolve_device
from .robots import FileRobotSpec, HandSpec, RobotLayout, RobotSpec, add_robot

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
    "RobotLayout",
    "RobotSpec",
    "add_robot",
    "catalog_object",
    "load_catalog",
    "load_mesh_object",
    "make_banana",
    "plan_pinch",
    "resolve_device",
]
