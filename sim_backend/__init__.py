"""Simulation backend: K worlds of hand + object per group on Newton, stepped as one graph."""

from .grasp import Grasp, plan_pinch
from .kinematics import Kinematics, SensorFK
from .objects import CATALOG, ObjectSpec, catalog_object, load_catalog, load_mesh_object, make_banana
from .observe import HEALTH_LOST, HEALTH_NAN, HEALTH_OK, Observation, add_sensor_noise
from .population import Population, PopulationConfig, SolverSettings, resolve_device
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
    "RobotLayout",
    "RobotSpec",
    "SensorFK",
    "SolverSettings",
    "add_robot",
    "add_sensor_noise",
    "catalog_object",
    "load_catalog",
    "load_mesh_object",
    "load_robot",
    "make_banana",
    "plan_pinch",
    "resolve_device",
]
