"""Simulation backend: K worlds of hand + object per group on Newton, stepped as one graph."""

from .build import BuiltModel, Physics, build_model, make_physics
from .config import PopulationConfig, SolverSettings, resolve_device
from .grasp import Grasp, plan_pinch
from .kinematics import Kinematics, SensorFK
from .objects import CATALOG, ObjectSpec, catalog_object, load_catalog, load_mesh_object, make_banana
from .observe import HEALTH_AWAY, HEALTH_LOST, HEALTH_NAN, HEALTH_OK, Observation, add_sensor_noise
from .params import ObjectParams
from .population import Population, no_collection
from .robots import FileRobotSpec, HandSpec, RobotLayout, RobotSpec, add_robot, load_robot

__all__ = [
    "CATALOG",
    "HEALTH_AWAY",
    "HEALTH_LOST",
    "HEALTH_NAN",
    "HEALTH_OK",
    "BuiltModel",
    "FileRobotSpec",
    "Grasp",
    "HandSpec",
    "Kinematics",
    "ObjectParams",
    "ObjectSpec",
    "Observation",
    "Physics",
    "Population",
    "PopulationConfig",
    "RobotLayout",
    "RobotSpec",
    "SensorFK",
    "SolverSettings",
    "add_robot",
    "add_sensor_noise",
    "build_model",
    "catalog_object",
    "load_catalog",
    "load_mesh_object",
    "load_robot",
    "make_banana",
    "make_physics",
    "no_collection",
    "plan_pinch",
    "resolve_device",
]
