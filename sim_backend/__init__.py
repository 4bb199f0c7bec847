"""Simulation backend: K worlds of hand + object per group on Newton, stepped as one graph."""

from .config import PopulationConfig, SolverSettings, forward_only_kernels, resolve_device

forward_only_kernels()  # before anything below imports newton: Warp reads the switch per kernel module

# isort: split
from .build import BuiltModel, Physics, build_model, make_physics  # noqa: E402
from .grasp import Grasp, plan_pinch  # noqa: E402
from .health import HEALTH_AWAY, HEALTH_LOST, HEALTH_NAN, HEALTH_OK  # noqa: E402
from .kinematics import Kinematics, SensorFK  # noqa: E402
from .objects import CATALOG, ObjectSpec, catalog_object, load_catalog, load_mesh_object, make_banana  # noqa: E402
from .observe import Observation, add_sensor_noise  # noqa: E402
from .params import ObjectParams  # noqa: E402
from .population import Population  # noqa: E402
from .robots import FileRobotSpec, HandSpec, RobotLayout, RobotSpec, add_robot, load_robot  # noqa: E402
from .step import no_collection  # noqa: E402

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
    "forward_only_kernels",
    "load_catalog",
    "load_mesh_object",
    "load_robot",
    "make_banana",
    "make_physics",
    "no_collection",
    "plan_pinch",
    "resolve_device",
]
