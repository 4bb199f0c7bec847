"""Ground truth for the accuracy benchmark: each suite's demos recorded with hidden physics drawn
from the tracker's prior, the truth's own physics gap and sensor noise; read from the bundled
files or the cache when they are there."""

from __future__ import annotations

import contextlib
import logging
import tempfile
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from filelock import FileLock

from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.evaluation import add_error
from inhand_tracker.service.paths import CACHE_DIR, DATA_DIR
from inhand_tracker.sim_backend import (
    Kinematics,
    Population,
    PopulationConfig,
    add_sensor_noise,
    catalog_object,
)
from inhand_tracker.sim_backend.objects import ObjectSpec
from inhand_tracker.sim_backend.robots import RobotSpec

from .demos import Demo
from .engines import truth_engine
from .kinds import make_kind
from .recorder import Recording, record
from .suites import SensorNoise, Suite, robot_spec

__all__ = ["ground_truth", "open_loop_disagreement"]

log = logging.getLogger(__name__)


def ground_truth(suite: Suite, device: str = "auto", cache: Path | None = CACHE_DIR) -> list[Trajectory]:
    """Every trajectory of ``suite``: read from the shipped files or ``cache``, else recorded (and
    written to ``cache``) with hidden mass and friction drawn from the tracker's prior (among those
    with which the hand keeps hold of the object): the demos (or a palm-carrying hand's palm
    motions) in the tracker's own simulator (one population per object, one group per physics draw
    of a demo), or the motions in MuJoCo C from the robot's MJCF or the suite's scene file
    (``suite.engine``)."""
    spec = robot_spec(suite.robot, suite.gap.finger_damping, suite.gap.servo_scale)
    kin = Kinematics(robot_spec(suite.robot))  # the robot's own model plans the demos
    on_palm = kin.layout.carries_on_palm  # palm motions; a hand that pinches gets the demos and motions
    if on_palm and suite.drop:
        raise ValueError(f"suite '{suite.name}': a drop is scripted for the procedural hand's carry only")
    # On the palm "held" is the object still lying there; a pinch must lift it 2 cm.
    margin = -0.03 if on_palm else 0.02
    out: list[Trajectory] = []
    for o, name in enumerate(suite.objects):
        obj = catalog_object(name)
        demos = [
            make_kind(kin, obj, kind, v, suite.seconds, suite.pace)
            for kind in suite.kinds
            for v in range(suite.variants)
        ]
        names = [f"{suite.name}-{d.name}.traj" for d in demos]
        # Runs started side by side on one machine (a paired comparison) must score one truth, and
        # a GPU's float atomics make every recording differ: the first records, the others wait and read it.
        with _locked(cache, f"{suite.name}-{name}"):
            found = (f for f in (DATA_DIR, cache) if f is not None and all((f / n).exists() for n in names))
            folder = next(found, None)
            if folder is not None:
                out += [Trajectory.load(folder / n) for n in names]
            else:
                rng = np.random.default_rng([suite.seed, o])
                out += _record(suite, kin, spec, obj, demos, names, rng, device, cache, margin)
    return out


def _locked(cache: Path | None, name: str) -> contextlib.AbstractContextManager:
    """The cache's lock on one object's truth (none without a cache)."""
    if cache is None:
        return contextlib.nullcontext()
    cache.mkdir(parents=True, exist_ok=True)
    return FileLock(cache / f"{name}.lock")


def _record(
    suite: Suite,
    kin: Kinematics,
    spec: RobotSpec,
    obj: ObjectSpec,
    demos: list[Demo],
    names: list[str],
    rng: np.random.Generator,
    device: str,
    cache: Path | None,
    margin: float,
) -> list[Trajectory]:
    """``obj``'s demos recorded by the suite's truth, with its sensors' noise; written to ``cache``."""
    name = obj.name
    out: list[Trajectory] = []
    log.info(f"recording ground truth: {name}, {len(demos)} demos of up to {max(d.frames for d in demos)} frames")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        xml = (cache or Path(tmp)) / f"{suite.name}-{name}.xml"
        engine = truth_engine(suite, kin, spec, obj, device, xml)
        tracks, rounds = engine.held(demos, rng, margin)
    if suite.drop:  # a scripted drop: the procedural hand's carry, in Newton
        held, drops = engine.dropped(demos, tracks[0][0])
        tracks = [(held, g) for _, g in tracks]
    for rec in {id(rec): rec for rec, _ in tracks}.values():  # each recording once, in order
        _add_sensor_noise(rec, suite.sensors, rng)
    seconds = time.perf_counter() - t0
    log.info(f"recorded {name} with {suite.engine}: {rounds} round(s) of physics draws in {seconds:.0f} s")
    meta = {
        "suite": suite.name,
        "engine": suite.engine,
        "gap": str(asdict(suite.gap)),
        "sensors": str(asdict(suite.sensors)),
    }
    for i, ((rec, g), d, file) in enumerate(zip(tracks, demos, names, strict=True)):
        event = {"drop_frame": int(drops[i])} if suite.drop else {}
        traj = rec.trajectory(g, suite.robot, name, meta | {"demo": d.name} | event)
        if cache is not None:
            traj.save(cache / file)
        out.append(traj)
    return out


def _add_sensor_noise(rec: Recording, noise: SensorNoise, rng: np.random.Generator) -> Recording:
    if noise != SensorNoise():
        add_sensor_noise(rec.sensing, rng, **asdict(noise))
    return rec


def open_loop_disagreement(
    trajectories: list[Trajectory],
    device: str = "auto",
    population: dict | None = None,
    servos: tuple = (),
) -> tuple[np.ndarray, np.ndarray]:
    """How far the tracker's own physics (with ``servos`` in place of its config's, a
    calibration's), started exactly where the truth started and given its hidden mass and
    friction, drifts from the truth over each track: ADD per frame, (F, n) [m], zero past a track's
    end; and how hard its hand presses against the truth's: the summed touch-zone (else fingertip)
    force over the summed true one, (n,). What no tracker can beat by simulating alone: where the
    drift is large the two engines disagree about the motion, and only the sensing can bring an
    estimate back."""
    obj = catalog_object(trajectories[0].object)
    config = PopulationConfig(groups=len(trajectories), worlds=1, device=device, **(population or {}))
    spec = robot_spec(trajectories[0].robot)
    pop = Population(replace(spec, servos=servos) if servos else spec, obj, config)
    demos = [Demo(t.name, t.controls, t.truth.initial_pose, t.truth.initial_q, phases=()) for t in trajectories]
    mass = np.array([t.truth.mass for t in trajectories], np.float32)
    friction = np.array([t.truth.friction for t in trajectories], np.float32)
    rec = record(pop, demos, mass, friction)
    truth = Recording.stack(trajectories)
    add = add_error(obj.surface_points(1000), truth.object_pose, rec.object_pose)
    within = np.arange(add.shape[0])[:, None] < truth.lengths[None]
    add[~within] = 0.0
    pressed = lambda r: (  # noqa: E731
        r.touch.sum(-1) if r.touch is not None and r.touch.size else np.linalg.norm(r.force, axis=-1).sum(-1)
    )
    ratio = (pressed(rec) * within).sum(0) / np.maximum((pressed(truth) * within).sum(0), 1e-9)
    return add, ratio
