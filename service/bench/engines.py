"""The suites' truth engines, one per suite engine (``Suite.engine``): Newton, the tracker's own
simulator with the suite's physics gap; MuJoCo C on the robot's model as Newton exports it; MuJoCo C
on a scene file written by others. Ground truth (:mod:`.truth`) and excitation recordings
(:mod:`.calibration`) both record through them; :func:`truth_engine` is the one place a suite's
engine is chosen."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from inhand_tracker.service.tracker import TrackerConfig
from inhand_tracker.sim_backend import Kinematics, Population, PopulationConfig, resolve_device
from inhand_tracker.sim_backend.objects import ObjectSpec
from inhand_tracker.sim_backend.robots import RobotSpec

from .demos import Demo
from .mujoco_truth import MujocoScene, export_scene, record_mujoco
from .recorder import Recording, record
from .scene_truth import load_scene
from .suites import Suite

__all__ = ["MujocoTruth", "NewtonTruth", "truth_engine"]

_TRUTH_SOLVER = {"tolerance": 1e-6, "ls_tolerance": 0.01}
"""The truth's solver converges as far as the solver's own defaults take it: the tracker's
looser budget is a speed setting, and a truth recorded with it would move with it (and no
longer match a cached one)."""
_CANDIDATES = 4
"""Hidden physics drawn per demo and recorded side by side on a CPU (4x that on a GPU); the first
that holds is kept."""
_DRAWS = 32
"""Hidden physics tried per demo at most before the recording gives up."""


@dataclass(frozen=True)
class NewtonTruth:
    """The truth in the tracker's own simulator, with the suite's physics gap, one world per group."""

    suite: Suite
    spec: RobotSpec
    """The robot as the truth has it (the gap's damping and servos)."""
    obj: ObjectSpec
    device: str

    def population(self, groups: int) -> Population:
        """``groups`` worlds of the truth's robot and object (the gap's size and physics)."""
        gap = self.suite.gap
        config = PopulationConfig(
            groups=groups, worlds=1, device=self.device, substeps=gap.substeps, impratio=gap.impratio,
            ramp_targets=gap.ramp_targets, **_TRUTH_SOLVER,
        )  # fmt: skip
        return Population(self.spec, self.obj.scaled(gap.object_scale), config)

    def record_one(self, demo: Demo, mass: float, friction: float) -> Recording:
        """``demo`` with hidden ``mass`` [kg] and ``friction``."""
        return record(self.population(1), demo, np.array([mass]), np.array([friction]))

    def held(self, demos: list[Demo], rng: np.random.Generator, margin: float) -> tuple[list, int]:
        """Each demo recorded with hidden physics with which the object stays in the hand: the
        tracks as (recording, its group) and how many rounds of draws it took."""
        # A GPU's frame costs little more for more worlds, so it tries a demo's draws side by side
        # rather than one round after another (a redrawn round costs a whole demo's time).
        candidates = _CANDIDATES if resolve_device(self.device).is_cpu else 4 * _CANDIDATES
        rec, rounds = _held_recording(self.population(len(demos) * candidates), demos, rng, margin)
        return [(rec, g) for g in range(len(demos))], rounds

    def dropped(self, demos: list[Demo], held: Recording) -> tuple[Recording, np.ndarray]:
        """The demos recorded again with the physics drawn for ``held``, the object slipping out of
        the hand from the middle of the first carry. Returns the recording and each demo's drop frame."""
        at = np.empty(len(demos), np.int64)
        for g, d in enumerate(demos):
            starts = dict(reversed(d.phases))
            carry_end = next(i for name, i in d.phases if i > starts["carry"] and name != "carry")
            at[g] = (starts["carry"] + carry_end) // 2
        return record(self.population(len(demos)), demos, held.mass, held.friction, slip_from=at), at


@dataclass(frozen=True)
class MujocoTruth:
    """The truth in MuJoCo C (one world: a track of its own per demo)."""

    scene: MujocoScene
    obj: ObjectSpec

    def record_one(self, demo: Demo, mass: float, friction: float) -> Recording:
        """``demo`` with hidden ``mass`` [kg] and ``friction``."""
        return record_mujoco(self.scene, demo, mass, friction)

    def held(self, demos: list[Demo], rng: np.random.Generator, margin: float) -> tuple[list, int]:
        """Each motion recorded with the first hidden mass and friction drawn from the prior with
        which the object stays in the hand (``margin`` as :meth:`Recording.held`'s): the tracks as
        (recording, 0) and the most draws one took."""
        obj, out, most = self.obj, [], 1
        for d in demos:
            for draw in range(_DRAWS):
                mass = float(_draw_prior(obj.mass, obj.mass_range, rng, 1)[0])
                friction = float(_draw_prior(obj.friction, obj.friction_range, rng, 1)[0])
                rec = record_mujoco(self.scene, d, mass, friction)
                if rec.held([d], margin)[0]:
                    out.append((rec, 0))
                    most = max(most, draw + 1)
                    break
            else:
                raise RuntimeError(f"{d.name}: the object fell out of the hand with all {_DRAWS} physics drawn")
        return out, most


def truth_engine(
    suite: Suite, kin: Kinematics, spec: RobotSpec, obj: ObjectSpec, device: str, xml: Path
) -> NewtonTruth | MujocoTruth:
    """``suite``'s truth engine for ``obj``: its scene file's, the robot's model exported to ``xml``
    for MuJoCo C, or Newton's."""
    if suite.engine == "newton":
        return NewtonTruth(suite, spec, obj, device)
    if suite.scene is not None:
        return MujocoTruth(load_scene(suite.scene, kin.layout, obj.mass, suite.gap.servo_scale), obj)
    return MujocoTruth(export_scene(spec, obj.scaled(suite.gap.object_scale), xml), obj)


def _draw_prior(nominal: float, bounds: tuple[float, float], rng: np.random.Generator, n: int) -> np.ndarray:
    """The tracker's prior over a physics parameter (its nominal value, a quarter of the range as
    standard deviation, clipped to the range): the truth is one draw from what the tracker believes."""
    lo, hi = bounds
    return np.clip(rng.normal(nominal, TrackerConfig().seeding.mass_sigma0 * (hi - lo), n), lo, hi)


def _held_recording(
    truth: Population, demos: list, rng: np.random.Generator, margin: float = 0.02
) -> tuple[Recording, int]:
    """Each demo recorded with hidden mass and friction drawn from the prior, among those with
    which the object stays in the hand from the lift to the set-down.

    A teleoperator whose object slipped out of the grasp would redo the demo: tracking an object
    that fell and tumbled on the table, unseen and untouched, is not what the paper measures. The
    draws are tried G / len(demos) at a time per demo, as groups of ``truth``, up to ``_DRAWS``.
    Returns the recording and how many rounds of draws it took.
    """
    obj, n, c = truth.object, len(demos), truth.G // len(demos)
    rounds = -(-_DRAWS // c)
    kept: list[tuple[Recording, int] | None] = [None] * n
    candidates = [d for d in demos for _ in range(c)]
    for r in range(rounds):
        mass = _draw_prior(obj.mass, obj.mass_range, rng, n * c)
        friction = _draw_prior(obj.friction, obj.friction_range, rng, n * c)
        rec = record(truth, candidates, mass, friction)
        held = rec.held(candidates, margin).reshape(n, c)
        for i in np.flatnonzero(held.any(axis=1)):
            kept[i] = kept[i] or (rec, int(i * c + held[i].argmax()))
        if all(kept):
            return Recording.gather(kept), r + 1
    lost = [d.name for d, k in zip(demos, kept, strict=True) if k is None]
    raise RuntimeError(f"{obj.name}: the object fell out of the hand with all {rounds * c} physics drawn for {lost}")
