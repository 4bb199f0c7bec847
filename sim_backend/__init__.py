"""Simulation backend: K worlds of hand + object per group on Newton, stepped as one graph.

Its names load on first use (lazy_loader): the settings (:class:`PopulationConfig`) are read and
checked without torch, warp's kernels or newton, which take seconds to import."""

import lazy_loader as lazy

from .config import forward_only_kernels

forward_only_kernels()  # before anything here imports newton: Warp reads the switch per kernel module

__getattr__, __dir__, __all__ = lazy.attach(
    __name__,
    submod_attrs={
        "config": ["PopulationConfig", "SolverSettings", "forward_only_kernels", "resolve_device"],
        "build": ["BuiltModel", "Physics", "build_model", "make_physics"],
        "grasp": ["Grasp", "plan_pinch"],
        "health": ["HEALTH_AWAY", "HEALTH_LOST", "HEALTH_NAN", "HEALTH_OK"],
        "kinematics": ["Kinematics", "SensorFK"],
        "objects": ["CATALOG", "ObjectSpec", "catalog_object", "load_catalog", "load_mesh_object", "make_banana"],
        "observe": ["Observation", "add_sensor_noise"],
        "params": ["ObjectParams"],
        "population": ["Population"],
        "robots": ["FileRobotSpec", "HandSpec", "RobotLayout", "RobotSpec", "add_robot", "load_robot"],
        "step": ["no_collection"],
    },
)
