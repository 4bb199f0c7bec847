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
from inhand_tracker.sim_backend import Kinematics, add_sensor_noise, catalog_object

from .engines import truth_engine
from .excitation import excitation_demo
from .shadow_motions import DISTAL_COUPLING, distal_coupling
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
    with tempfile.TemporaryDirectory() as tmp:
        engine = truth_engine(suite, kin, spec, obj, device, Path(tmp) / "robot.xml")
        rec = engine.record_one(demo, obj.mass, obj.friction)
    if suite.sensors != SensorNoise():
        add_sensor_noise(rec.sensing, np.random.default_rng([suite.seed, seed, 7]), **asdict(suite.sensors))
    meta = {"suite": suite.name, "engine": suite.engine, "calibration": "free motion, object out of reach"}
    return rec.trajectory(0, suite.robot, obj.name, meta)
