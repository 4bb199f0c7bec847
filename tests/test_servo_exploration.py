"""Servo exploration: the worlds scale each finger's servos by a strength of their own, drawn where
the model check says the hand does not follow the robot's joints, and resampling keeps the
strengths whose joints do; a matched robot's worlds keep the config's servos."""

from __future__ import annotations

from dataclasses import replace

import newton
import numpy as np
import pytest
import torch

from inhand_tracker.service.bench.demos import make_demo
from inhand_tracker.service.bench.recorder import record
from inhand_tracker.service.paths import CONFIG_DIR
from inhand_tracker.service.tracker import Frame, Tracker, tracker_config
from inhand_tracker.service.tracker.servos import SCALED_SERVOS
from inhand_tracker.sim_backend import (
    HandSpec,
    Kinematics,
    Population,
    PopulationConfig,
    add_robot,
    catalog_object,
    load_robot,
)
from inhand_tracker.sim_backend.kinematics import joint_chains

OBJECT = "foam_brick"


def _chains(spec) -> dict[int, list[str]]:
    builder = newton.ModelBuilder()
    newton.solvers.SolverMuJoCo.register_custom_attributes(builder)
    layout = add_robot(builder, spec)
    replicated = newton.ModelBuilder()
    replicated.replicate(builder, 2)
    out: dict[int, list[str]] = {}
    for name, chain in zip(layout.joint_names, joint_chains(replicated.finalize(device="cpu"), layout), strict=True):
        out.setdefault(int(chain), []).append(name)
    return out


def test_joint_chains_are_the_fingers_and_the_wrist():
    assert _chains(load_robot(CONFIG_DIR / "robots/allegro_palm.toml")) == {
        c: [f"{finger}j{i}" for i in range(4)] for c, finger in enumerate(("ff", "mf", "rf", "th"))
    }
    shadow = _chains(load_robot(CONFIG_DIR / "robots/shadow_touch.toml"))
    assert [names[0] for names in shadow.values()] == [
        f"robot0:{j}" for j in ("WRJ1", "FFJ3", "MFJ3", "RFJ3", "LFJ4", "THJ4")
    ]
    assert [len(names) for names in shadow.values()] == [2, 4, 4, 4, 5, 5]
    hand = _chains(HandSpec())
    assert len(hand[0]) == 6 and hand[0][0] == "wrist_x" and [len(n) for n in hand.values()] == [6, 4, 4, 4, 4]
    assert _chains(load_robot(CONFIG_DIR / "robots/example_gripper.toml")) == {0: ["left_slide"], 1: ["right_slide"]}


@pytest.fixture(scope="module")
def weak_index():
    """A pick and place by the procedural hand whose index finger's servos are half as strong as
    its config's (gain, damping and effort limit), and the hand's config."""
    spec, obj = HandSpec(), catalog_object(OBJECT)
    kin = Kinematics(spec)
    demo = make_demo(kin, obj, "pick_place", 0, seconds=3.0, pace=0.7).until("place")
    config = Population(spec, obj, PopulationConfig(groups=1, worlds=1, device="cpu"))
    index = np.array([name.startswith("index") for name in kin.layout.joint_names])
    servos = tuple((n, tuple(np.where(index, 0.5, 1.0) * config.servos(n)[0, 0].numpy())) for n in SCALED_SERVOS)
    truth = Population(replace(spec, servos=servos), obj, PopulationConfig(groups=1, worlds=1, device="cpu"))
    return spec, record(truth, demo, np.array([obj.mass]), np.array([obj.friction]))


_EXPLORED = {"servos.servo_sigma0": 0.5, "servos.servo_gate": 0.01, "servos.servo_gate_updates": 2}


def _track(spec, rec, methods, **settings) -> Tracker:
    pop = Population(spec, catalog_object(OBJECT), PopulationConfig(groups=len(methods), worlds=16, device="cpu"))
    tracker = Tracker(pop, tracker_config({"update_every": 5, **settings}), methods)
    rows = np.zeros(len(methods), int)
    tracker.start(np.repeat(rec.initial_pose[:1], len(methods), 0), rec.initial_q[rows])
    for f in range(rec.frames):
        tracker.step(Frame(**{name: None if v is None else v[f, rows] for name, v in rec.sensing.items()}))
    return tracker


def test_the_worlds_find_the_weak_finger_and_keep_the_config_elsewhere(weak_index):
    """With the gate at 10 mrad, the index finger's chain opens and its strength falls to the
    truth's 0.5 (0.51 when written); the other fingers' joints follow the robot, so their chains
    stay shut on the config's servos; OLP's world simulates the config's."""
    spec, rec = weak_index
    tracker = _track(spec, rec, ["PBO", "OLP"], **_EXPLORED)
    servos = tracker.servos
    assert servos.names == ("wrist_x", "index_0", "middle_0", "ring_0", "thumb_0")
    assert servos.open.tolist() == [[False, True, False, False, False], [False] * 5], servos.open
    strength = {n: float(v[0]) for n, v in servos.strengths(tracker.weights()).items()}
    others = [strength[n] for n in servos.names if n != "index_0"]
    assert 0.35 < strength["index_0"] < 0.7 and others == [1.0] * 4, strength
    pop = tracker.pop
    assert torch.equal(pop.servos("ke")[1], servos.nominal["ke"][1]), "OLP simulates the config's servos"
    ratio = pop.servos("effort")[0] / servos.nominal["effort"][0]
    assert torch.allclose(ratio, pop.servos("ke")[0] / servos.nominal["ke"][0]), "gain and effort scale together"
    tracker.start(np.repeat(rec.initial_pose[:1], 2, 0), rec.initial_q[[0, 0]])
    assert not servos.open.any() and torch.equal(pop.servos("ke"), servos.nominal["ke"]), "a new session: the config's"


def test_a_robot_that_matches_its_config_keeps_its_servos(weak_index):
    spec, _ = weak_index
    obj = catalog_object(OBJECT)
    demo = make_demo(Kinematics(spec), obj, "pick_place", 0, seconds=3.0, pace=0.7).until("place")
    truth = Population(spec, obj, PopulationConfig(groups=1, worlds=1, device="cpu"))
    rec = record(truth, demo, np.array([obj.mass]), np.array([obj.friction]))
    tracker = _track(spec, rec, ["PBO"], **_EXPLORED)
    assert not tracker.servos.open.any(), (tracker.joints.rms() * 1e3).round()
    assert torch.equal(tracker.pop.servos("ke"), tracker.servos.nominal["ke"])
