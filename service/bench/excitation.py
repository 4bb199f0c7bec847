"""A suite's excitation recording, what `calibrate` fits a robot's servos to: the hand moves every
joint on its own, the object out of its reach, so that each servo's stiffness and damping show in
how its joint follows; recorded by the suite's truth (its engine, servos, contact settings and
sensor noise) apart from the tracked tracks.

Each joint steps between targets drawn across most of its range, held 0.3-0.8 s, with fast
minimum-jerk moves between them (a servo's gain shows in how far it lags and overshoots, its
damping in how it settles); the joints step at their own times, so one joint's motion is not
confused with another's.
"""

from __future__ import annotations

import tempfile
from dataclasses import asdict
from pathlib import Path

import numpy as np

from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.calibration.servos import out_of_reach
from inhand_tracker.sim_backend import Kinematics, add_sensor_noise, catalog_object
from inhand_tracker.sim_backend.objects import ObjectSpec

from .demos import FRAME_RATE, Demo
from .engines import truth_engine
from .scripting import minimum_jerk
from .shadow_motions import DISTAL_COUPLING, distal_coupling
from .suites import SensorNoise, Suite, robot_spec

__all__ = ["excitation_demo", "excitation_recording"]

_MOVE = 0.05
"""How long a step between targets takes [s]."""


def excitation_demo(
    kin: Kinematics,
    obj: ObjectSpec,
    seconds: float = 20.0,
    seed: int = 0,
    follow: tuple[list[int], list[int], float] | None = None,
) -> Demo:
    """``seconds`` of every joint stepping through its range, the object lying a metre away.
    ``follow`` (leaders, followers, ratio): joints the robot's driver commands as a multiple of
    others (a tendon-coupled finger's distal joint), as it would."""
    if not (2.0 <= seconds <= 300.0):
        raise ValueError(f"excitation seconds: expected 2 to 300, got {seconds}")
    lay = kin.layout
    rng = np.random.default_rng(seed)
    frames = round(seconds * FRAME_RATE)
    lo, hi = lay.lower + 0.1 * (lay.upper - lay.lower), lay.upper - 0.1 * (lay.upper - lay.lower)
    controls = np.empty((frames, lay.dof_count))
    t = np.arange(frames) / FRAME_RATE
    for j in range(lay.dof_count):
        q, at, path = lay.default_q[j], 0.0, np.empty(frames)
        while at < seconds:
            hold = rng.uniform(0.3, 0.8)
            target = rng.uniform(lo[j], hi[j])
            span = (t >= at) & (t < at + hold)
            progress = minimum_jerk(np.clip((t[span] - at) / _MOVE, 0.0, 1.0))
            path[span] = q + (target - q) * progress
            q, at = target, at + hold
        controls[:, j] = path
    if follow is not None:
        leaders, followers, ratio = follow
        controls[:, followers] = np.clip(ratio * controls[:, leaders], lay.lower[followers], lay.upper[followers])
    return Demo(f"{obj.name}_excitation_{seed}", controls.astype(np.float32), out_of_reach(obj),
                lay.default_q.astype(np.float32), phases=(("move", 0),))  # fmt: skip


def excitation_recording(suite: Suite, device: str = "auto", seconds: float = 20.0, seed: int = 1) -> Trajectory:
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
    meta = {"suite": suite.name, "engine": suite.engine, "excitation": "free motion, object out of reach"}
    return rec.trajectory(0, suite.robot, obj.name, meta)
