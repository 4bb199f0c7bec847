"""The manipulate suite: Gymnasium-Robotics' HandManipulateBlockTouchSensors scene as its authors
ship it, run in MuJoCo C as the truth, its 92 touch sensors as the robot's touch array, and the
tracker on its own config of that hand (`shadow_touch`)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from inhand_tracker.service.bench.demos import Demo
from inhand_tracker.service.bench.mujoco_truth import record_mujoco
from inhand_tracker.service.bench.recorder import record
from inhand_tracker.service.bench.scene_truth import (
    MANIPULATE_BLOCK,
    MANIPULATE_BLOCK_TIPS,
    MANIPULATE_EGG_TIPS,
    MANIPULATE_PEN_TIPS,
    SceneFile,
    load_scene,
)
from inhand_tracker.service.bench.shadow_motions import PALM_CENTRE, SHADOW_MOTION_KINDS, make_shadow_motion
from inhand_tracker.service.bench.suites import robot_spec
from inhand_tracker.service.cli import app
from inhand_tracker.sim_backend import Kinematics, Population, PopulationConfig, add_sensor_noise, catalog_object
from inhand_tracker.sim_backend.robot_specs import FileRobotSpec

GRAVITY = 9.81


@pytest.fixture(scope="module")
def hand():
    spec = robot_spec("shadow_touch")
    return spec, Kinematics(spec)


@pytest.fixture(scope="module")
def roll(hand):
    """A roll of the block on the palm, in the package's scene and in the tracker's physics."""
    spec, kin = hand
    obj = catalog_object("block")
    demo = make_shadow_motion(kin, obj, "roll", seconds=8.0)
    scene = load_scene(MANIPULATE_BLOCK, kin.layout, obj.mass)
    truth = record_mujoco(scene, demo, mass=obj.mass, friction=obj.friction)
    ours = record(Population(spec, obj, PopulationConfig(groups=1, worlds=1, device="cpu")), demo,
                  np.array([obj.mass]), np.array([obj.friction]))  # fmt: skip
    return scene, demo, truth, ours


def test_the_robot_config_takes_its_touch_zones_from_the_models_touch_sites(hand):
    _, kin = hand
    names = kin.layout.zone_names
    assert len(names) == 92 and names[0] == "robot0:T_palm_b0"
    palm = kin.layout.zone_boxes[0]  # the site's box as the package writes it
    assert palm == pytest.approx([0.011, -0.005, 0.006, 0.033, 0.007, 0.019])
    tip = kin.layout.zone_boxes[names.index("robot0:T_fftip_tip")]
    assert tip[3:] == pytest.approx([0.008] * 3)  # a sphere site: its bounding cube


def test_a_touch_sites_pattern_that_matches_nothing_is_named(hand):
    spec, _ = hand
    assert isinstance(spec, FileRobotSpec)
    with pytest.raises(ValueError, match=r"robot 'shadow_touch' touch_sites: no site of .* matches 'robot0:X_.\*'"):
        Kinematics(replace(spec, touch_sites="robot0:X_.*"))
    with pytest.raises(ValueError, match=r"touch_sites: not a regular expression"):
        Kinematics(replace(spec, touch_sites="(["))


def test_the_scene_is_the_packages_own(roll):
    scene, *_ = roll
    m = scene.model
    assert m.opt.timestep == pytest.approx(1 / 30 / 17)  # its 2 ms step, as near as 30 Hz frames allow
    assert m.nu == 20 and len(scene.touch_sensors) == 92  # its actuators; no servo on a distal joint
    assert m.body(scene.object_body).name == "object" and m.geom("object").size == pytest.approx([0.025] * 3)
    with pytest.raises(ValueError, match=r"scene 'manipulate_block_touch_sensors.xml': no body 'mug'"):
        load_scene(SceneFile(MANIPULATE_BLOCK.path, "mug"), Kinematics(robot_spec("shadow_touch")).layout, 0.07)


def test_the_block_stays_on_the_palm_and_its_weight_is_felt_there(roll):
    _, demo, truth, ours = roll
    assert truth.held([demo], margin=-0.03)[0]
    assert truth.force is None and truth.slip is None  # the scene's hand has no fingertip sensors
    assert truth.touch.shape == (demo.frames, 1, 92)
    mass = catalog_object("block").mass
    settled = slice(8, 17)  # resting on the open palm before the fingers move
    weight = mass * GRAVITY
    felt = truth.touch[settled, 0].sum(-1)
    assert np.all(np.abs(felt - weight) < 0.25 * weight), (felt, weight)
    # The tracker's worlds feel it on the same zones: the same sites on the same links. Each contact
    # presses one zone of its link, where the truth's sensors feel it: on a phalanx's surface, not
    # on its capsule's axis where its four zones meet.
    ours_felt = ours.touch[settled, 0]
    assert np.all(np.abs(ours_felt.sum(-1) - weight) < 0.05 * weight), ours_felt.sum(-1)
    pressed = lambda t: set(np.flatnonzero(t[settled, 0].mean(0) > 0.05 * weight))  # noqa: E731
    assert pressed(truth.touch) & pressed(ours.touch), (pressed(truth.touch), pressed(ours.touch))
    both = sorted(pressed(truth.touch) & pressed(ours.touch))
    # How the weight shares out among the palm and the fingers' bases is the engine's: the worlds
    # collide as MuJoCo-Warp does, which on the scene file itself reads what they read here (0.127,
    # 0.224, 0.151 N on these zones) where MuJoCo C reads 0.083, 0.234, 0.178.
    np.testing.assert_allclose(ours_felt.mean(0)[both], truth.touch[settled, 0].mean(0)[both], rtol=0.6)


@pytest.mark.slow
def test_the_manipulate_suite_in_short_form_tracks_the_block_on_the_palm(tmp_path):
    out = tmp_path / "out"
    args = ["bench", "accuracy", "--suite", "manipulate", "--short", "--methods", "OLP,PBO", "--noise", "med"]
    args += ["--worlds", "8", "--device", "cpu", "--out", str(out), "--cache", str(tmp_path / "cache")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    results = json.loads((out / "results.json").read_text())
    assert results["suite"]["engine"] == "scene" and results["suite"]["name"] == "manipulate-short"
    summary = {m: results["summary"][m]["med"]["mean_mm"] for m in ("OLP", "PBO")}
    # On the palm, not lost (a hypothesis off the hand costs 100 mm or more); the accuracy is a
    # claim over many starts at K=40 and 1024, for the GPU benchmark.
    assert max(summary.values()) < 40.0, summary
    assert "manipulate_block_touch_sensors.xml" in (out / "report.md").read_text()
    assert sorted(p.name for p in (tmp_path / "cache").glob("*.traj")) == [
        f"manipulate-short-block_{k}_0.traj" for k in sorted(SHADOW_MOTION_KINDS[:2])
    ]


def test_a_hand_with_fingertip_sensors_feels_the_scenes_contacts_on_its_fingertips():
    """The same scene felt as a Shadow hand with force sensors in its fingertips (the
    manipulate-fingertips suite): the truth reads the contact forces on the config's sensor links,
    and the tracker's worlds feel the fingers' pushes on the same fingertips."""
    spec = robot_spec("shadow_hand")
    kin, obj = Kinematics(spec), catalog_object("block")
    demo = make_shadow_motion(kin, obj, "roll", seconds=8.0)
    scene = load_scene(MANIPULATE_BLOCK_TIPS, kin.layout, obj.mass)
    assert [scene.model.body(int(b)).name for b in scene.sensor_bodies] == list(spec.sensor_links)
    truth = record_mujoco(scene, demo, mass=obj.mass, friction=obj.friction)
    assert truth.touch.shape == (demo.frames, 1, 0) and truth.force.shape == (demo.frames, 1, 5, 3)
    ours = record(Population(spec, obj, PopulationConfig(groups=1, worlds=1, device="cpu")), demo,
                  np.array([obj.mass]), np.array([obj.friction]))  # fmt: skip
    pushing = lambda rec: np.linalg.norm(rec.force[:, 0], axis=-1) > 0.1  # noqa: E731 - (F, 5)
    assert pushing(truth).any(0).sum() >= 2, "the roll's fingers push the block"
    both = (pushing(truth) & pushing(ours)).sum() / pushing(truth).sum()
    assert both > 0.5, both
    assert not load_scene(MANIPULATE_BLOCK, kin.layout, obj.mass).sensor_bodies.size, "the touch scene's hand has none"


@pytest.mark.parametrize(("scene_file", "name"), [(MANIPULATE_EGG_TIPS, "egg"), (MANIPULATE_PEN_TIPS, "pen")])
def test_the_packages_egg_and_pen_lie_on_the_palm_as_the_catalogs_do(scene_file: SceneFile, name: str):
    """The package's egg and pen scenes hold the catalog's egg and pen (shape and mass), laid on the
    open palm on their sides; cradled, they stay in the hand, and one world of the tracker's physics
    started where the truth starts settles where it does."""
    spec = robot_spec("shadow_hand")
    kin, obj = Kinematics(spec), catalog_object(name)
    scene = load_scene(scene_file, kin.layout, obj.mass)
    m = scene.model
    assert m.body_mass[scene.object_body] == pytest.approx(obj.mass, rel=0.01)
    assert m.geom_aabb[m.geom("object").id, 3:] == pytest.approx(obj.mesh.extents / 2, abs=1e-4)  # its box
    demo = make_shadow_motion(kin, obj, "cradle", seconds=8.0)
    truth = record_mujoco(scene, demo, mass=obj.mass, friction=obj.friction)
    ours = record(Population(spec, obj, PopulationConfig(groups=1, worlds=1, device="cpu")), demo,
                  np.array([obj.mass]), np.array([obj.friction]))  # fmt: skip
    assert truth.held([demo], margin=-0.03)[0]
    lying = truth.object_pose[18, 0, 2] - (PALM_CENTRE[2] + np.min(obj.mesh.extents) / 2)
    assert abs(lying) < 0.03, "on its side on the palm, not stood on end"
    settled = np.linalg.norm(truth.object_pose[15:20, 0, :3] - ours.object_pose[15:20, 0, :3], axis=-1)
    assert settled.max() < 0.003, settled


def test_touch_noise_has_a_deadband_and_a_field_the_robot_lacks_stays_absent():
    touch = np.zeros((200, 1, 3), np.float32)
    touch[:, 0, 1], touch[:, 0, 2] = 0.05, 2.0  # a graze under the deadband, a press
    sensing = {"q": np.zeros((200, 1, 4), np.float32), "force": None, "slip": None, "spin": None, "touch": touch}
    add_sensor_noise(sensing, np.random.default_rng(0), joint_sigma=0.005, touch_sigma=0.05, touch_deadband=0.1)
    noisy = sensing["touch"][:, 0]
    assert (noisy[:, 0] == 0).all(), "an untouched zone reads nothing"
    assert (noisy[:, 1] == 0).mean() > 0.8, "under the deadband it reads 0 (but for noise past it)"
    assert abs(noisy[:, 2].std() - 0.05) < 0.01 and abs(noisy[:, 2].mean() - 2.0) < 0.02
    assert sensing["force"] is None and sensing["slip"] is None


def test_contact_capacity_is_sized_from_the_robot_and_object():
    """A block rolled over a Shadow hand's palm made over 32 contacts in a world (the old fixed
    capacity): the capacity is sized from the robot's collision shapes, unless set."""
    spec, obj = robot_spec("shadow_touch"), catalog_object("block")
    sized = Population(spec, obj, PopulationConfig(groups=1, worlds=2, device="cpu", use_graph=False)).config
    assert sized.contacts_per_world > 32 and sized.constraints_per_world == 5 * sized.contacts_per_world
    chosen = PopulationConfig(groups=1, worlds=2, device="cpu", use_graph=False, contacts_per_world=40)
    assert Population(spec, obj, chosen).config.contacts_per_world == 40


def test_the_hands_contact_pairs_collide_as_the_file_names_them(hand):
    """The scene's file lets the thumb press the fingers through explicit contact pairs while its
    collision masks keep the hand's links apart otherwise; the worlds simulate the pairs too, so
    their touch zones read the thumb pressing the first finger as the scene's sensors do."""
    spec, kin = hand
    obj = catalog_object("block")
    names = list(kin.layout.joint_names)
    pinch = kin.layout.default_q.copy()
    for joint, angle in {"THJ4": 0.9, "THJ3": 0.9, "FFJ2": 0.9, "FFJ1": 0.5, "FFJ0": 0.57}.items():
        pinch[names.index(f"robot0:{joint}")] = angle
    frames = 45
    ramp = np.clip(np.arange(frames) / 30, 0, 1)[:, None]
    controls = kin.layout.default_q + ramp * (pinch - kin.layout.default_q)
    away = np.array([1.0, 1.0, 0.025, 0.0, 0.0, 0.0, 1.0])  # the block out of reach
    demo = Demo("pinch", controls, away, kin.layout.default_q.copy(), phases=())
    pop = Population(spec, obj, PopulationConfig(groups=1, worlds=1, device="cpu"))
    # Frictionless, as the file's pairs say (condim 1): fingers pressing each other slide. The block
    # touches them with its own settings (its scenes' condim 4).
    to_shape = pop.solver.mjc_geom_to_newton_shape.numpy()[0]
    condim = {int(n): int(c) for n, c in zip(to_shape, pop.solver.mj_model.geom_condim, strict=True) if n >= 0}
    label = list(pop.model.shape_label)
    shape = lambda name: next(i for i, lbl in enumerate(label) if lbl.endswith(name))  # noqa: E731
    shapes = ("robot0:C_thdistal", "robot0:C_ffdistal", "robot0:C_palm0", "block")
    assert [condim[shape(n)] for n in shapes] == [1, 1, 1, 4]
    touch = record(pop, demo, np.array([obj.mass]), np.array([obj.friction])).touch[-10:, 0].mean(0)
    zones = kin.layout.zone_names
    felt = lambda *links: sum(t for t, z in zip(touch, zones, strict=True) if z.startswith(links))  # noqa: E731
    first_finger, thumb = felt("robot0:T_ffmiddle", "robot0:T_ffdistal"), felt("robot0:T_thmiddle", "robot0:T_thtip")
    assert first_finger > 0.05 and thumb > 0.05, (first_finger, thumb)
    assert felt("robot0:T_rf", "robot0:T_lf") == 0.0  # links no pair names stay apart
