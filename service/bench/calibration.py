"""A suite's calibration recording: its robot moving every joint on its own, the object out of
reach, recorded by the suite's truth (its engine, its servos and contact settings, its sensor
noise) apart from the tracked tracks; what `calibrate` fits the tracker's servos to before a suite
is tracked with them."""

from __future__ import annotations

import tempfile
from dataclasses import asdict
from pathlib import Path

import numpy as np

from inhand_tracker.protocol import Trajectory
from inhand_tracker.sim_backend import Kinematics, Population, PopulationConfig, add_sensor_noise, catalog_object

from .excitation import excitation_demo
from .mujoco_truth import export_scene, record_mujoco
from .palm_motions import DISTAL_COUPLING, distal_coupling
from .recorder import record
from .scene_truth import load_scene
from .suites import SensorNoise, Suite, robot_spec

__all__ = ["calibration_recording"]


def calibration_recording(suite: Suite, device: str = "auto", seconds: float = 20.0, seed: int = 1) -> Trajectory:
    """``seconds`` of the suite's robot stepping every joint through its range, recorded by the
    suite's truth with its sensor noise (the joints' noise is what a calibration sees)."""
    spec = robot_spec(suite.robot, suite.gap.finger_damping, suite.gap.servo_scale)
    kin = Kinematics(robot_spec(suite.robot))
    obj = catalog_object(suite.objects[0])
    coupled = distal_coupling(kin.layout)  # a Shadow Hand's driver commands its distal joints so
    demo = excitation_demo(kin, obj, seconds, seed, (*coupled, DISTAL_COUPLING) if coupled else None)
    mass, friction = np.array([obj.mass]), np.array([obj.friction])
    if suite.engine == "scene" and suite.scene is not None:
        scene = load_scene(suite.scene, kin.layout, obj.mass, suite.gap.servo_scale)
        rec = record_mujoco(scene, demo, obj.mass, obj.friction)
    elif suite.engine == "mujoco":
        with tempfile.TemporaryDirectory() as tmp:
            scene = export_scene(spec, obj.scaled(suite.gap.object_scale), Path(tmp) / "robot.xml")
            rec = record_mujoco(scene, demo, obj.mass, obj.friction)
    else:
        gap = suite.gap
        config = PopulationConfig(
            groups=1, worlds=1, device=device, substeps=gap.substeps, impratio=gap.impratio,
            ramp_targets=gap.ramp_targets, tolerance=1e-6, ls_tolerance=0.01,
        )  # fmt: skip
        rec = record(Population(spec, obj.scaled(gap.object_scale), config), demo, mass, friction)
    if suite.sensors != SensorNoise():
        add_sensor_noise(rec.sensing, np.random.default_rng([suite.seed, seed, 7]), **asdict(suite.sensors))
    meta = {"suite": suite.name, "engine": suite.engine, "calibration": "free motion, object out of reach"}
    return rec.trajectory(0, suite.robot, obj.name, meta)
