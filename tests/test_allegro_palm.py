"""The Allegro Hand palm up: the project's own model of it (``configs/robots/allegro_palm``), its
scene in MuJoCo C as the truth with its 14 touch sensors as the robot's touch array, and motions
in which the fingers push and the thumb slides the block lying on the palm."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from inhand_tracker.service.bench.allegro_motions import ALLEGRO_MOTION_KINDS, make_allegro_motion
from inhand_tracker.service.bench.mujoco_truth import record_mujoco
from inhand_tracker.service.bench.scene_truth import ALLEGRO_PALM_BLOCK, ALLEGRO_PALM_BLOCK_TIPS, load_scene
from inhand_tracker.service.bench.suites import SUITES, robot_spec
from inhand_tracker.service.cli import app
from inhand_tracker.sim_backend import Kinematics, catalog_object

GRAVITY = 9.81


@pytest.fixture(scope="module")
def hand():
    return Kinematics(robot_spec("allegro_palm"))


@pytest.fixture(scope="module")
def scene(hand):
    return load_scene(ALLEGRO_PALM_BLOCK, hand.layout, catalog_object("block").mass)


def test_the_model_has_the_hands_joints_limits_and_touch_array(hand):
    lay = hand.layout
    assert len(lay.joint_names) == 16 and lay.joint_names[12] == "thj0"
    # the thumb's rotation starts at its lower limit, the published 0.263 rad
    assert lay.lower[12] == pytest.approx(0.263) and lay.default_q[12] == pytest.approx(0.263)
    assert lay.upper[1] == pytest.approx(1.61) and lay.lower[0] == pytest.approx(-0.47)
    assert len(lay.zone_names) == 14 and lay.zone_names[:2] == ("T_palm_top", "T_palm_bottom")


def test_the_scene_drives_every_joint_and_senses_every_zone(scene, hand):
    m = scene.model
    assert m.nu == 16 and sorted(scene.actuator_joint.tolist()) == list(range(16))
    assert len(scene.touch_sensors) == 14
    assert m.opt.cone == 0 and m.opt.impratio == pytest.approx(1.0)  # MuJoCo's own contact model


def test_the_fingertip_config_feels_the_scene_through_its_fingertip_links_alone():
    """allegro_palm_tips: the same hand without its touch array; the scene's truth reads the contact
    forces on the config's fingertip links, and no touch sensor."""
    tips = Kinematics(robot_spec("allegro_palm_tips")).layout
    assert tips.zone_names == () and tips.sensor_names == ("ff_distal", "mf_distal", "rf_distal", "th_distal")
    scene = load_scene(ALLEGRO_PALM_BLOCK_TIPS, tips, catalog_object("block").mass)
    assert [scene.model.body(int(b)).name for b in scene.sensor_bodies] == list(tips.sensor_names)
    assert len(scene.touch_sensors) == 0 and scene.sensor_offsets.shape == (4, 7)
    assert SUITES["allegro-palm-fingertips"].robot == "allegro_palm_tips"


def test_a_weak_servos_truth_scales_the_scene_s_servos_and_the_robot_s(scene, hand):
    """The suite whose truth's servos are half the config's: gain, damping and force range halved
    in the scene, and in the robot spec a Newton truth would use."""
    weak = load_scene(ALLEGRO_PALM_BLOCK, hand.layout, catalog_object("block").mass, servo_scale=0.5)
    m, w = scene.model, weak.model
    np.testing.assert_allclose(w.actuator_gainprm[:, 0], 0.5 * m.actuator_gainprm[:, 0])
    np.testing.assert_allclose(w.actuator_biasprm[:, 1:3], 0.5 * m.actuator_biasprm[:, 1:3])
    np.testing.assert_allclose(w.actuator_forcerange, 0.5 * m.actuator_forcerange)
    dofs = m.jnt_dofadr[[m.joint(n).id for n in hand.layout.joint_names]]
    np.testing.assert_allclose(w.dof_damping[dofs], 0.5 * m.dof_damping[dofs])
    assert m.actuator_gainprm[0, 0] == pytest.approx(10.0)  # the config's 10 N m/rad, unchanged
    assert SUITES["allegro-palm-weak"].gap.servo_scale == 0.5
    spec = robot_spec("allegro_palm", servo_scale=0.5)
    assert (spec.ke[0], spec.kd[0], spec.effort[0]) == pytest.approx((5.0, 0.0, 0.35))


def test_the_tracker_s_model_damps_each_joint_as_the_scene_does(scene, hand):
    """The file gives the joints their damping; the servos add none (kd = 0), so each joint is
    damped once, as in the scene, not by the file's damping and the servo's both."""
    from inhand_tracker.sim_backend import Population, PopulationConfig

    pop = Population(robot_spec("allegro_palm"), catalog_object("block"), PopulationConfig(worlds=1, device="cpu"))
    dofs = pop.layout.dof_indices
    passive, servo = pop.model.joint_damping.numpy()[dofs], pop.model.joint_target_kd.numpy()[dofs]
    m = scene.model
    truth = m.dof_damping[m.jnt_dofadr[[m.joint(n).id for n in hand.layout.joint_names]]]
    np.testing.assert_allclose(passive + servo, truth, rtol=1e-6)


def test_the_weak_truth_s_own_numbers_replay_its_joints_once_the_joint_damping_is_among_them():
    """The weak suite's excitation recording replayed by the tracker's engine with the truth's
    servos (gain 5, force limit 0.35) follows the measured joints within their noise (5 mrad) only
    with the truth's joint damping as well (0.1, half the file's): the file's 0.2 caps the fingers'
    speed at the force limit over the damping, half the truth's."""
    import torch

    from inhand_tracker.service.bench.excitation import excitation_recording
    from inhand_tracker.service.calibration.servos import _replay, _series
    from inhand_tracker.sim_backend import Population, PopulationConfig

    rec = excitation_recording(SUITES["allegro-palm-weak"], "cpu", seconds=8.0)
    obj = catalog_object(rec.object)
    pop = Population(robot_spec("allegro_palm"), obj, PopulationConfig(groups=1, worlds=2, device="cpu"))
    series = _series([rec], obj, pop.torch_device)
    servos = {"ke": 5.0, "kd": 0.0, "effort": 0.35}
    servos = {k: torch.full((2, pop.D), v) for k, v in servos.items()} | {"damping": torch.tensor([[0.1], [0.2]])}
    rms = np.sqrt(_replay(pop, series, {k: v.expand(2, pop.D) for k, v in servos.items()}).numpy() / series.frames)
    assert np.median(rms[0]) < 0.008 and rms[0].max() < 0.012, rms[0]
    assert np.median(rms[1]) > 0.03, rms[1]


@pytest.mark.parametrize("kind", ["push", "slide"])
def test_the_block_stays_on_the_palm_moves_and_its_weight_is_felt_there(scene, hand, kind):
    obj = catalog_object("block")
    demo = make_allegro_motion(hand, obj, kind, seconds=8.0)
    truth = record_mujoco(scene, demo, mass=obj.mass, friction=obj.friction)
    assert truth.held([demo], margin=-0.03)[0]
    assert truth.force is None and truth.touch.shape == (demo.frames, 1, 14)
    settled = slice(8, 17)  # lying on the palm before the hand moves
    felt = truth.touch[settled, 0].sum(axis=1)
    assert felt.mean() == pytest.approx(obj.mass * GRAVITY, rel=0.1)
    assert truth.touch[settled, 0, :2].sum(axis=1).mean() > 0.5 * obj.mass * GRAVITY  # mostly by the palm
    path = truth.object_pose[:, 0, :2]
    assert np.ptp(path, axis=0).max() > 0.004  # the fingers or thumb moved it on the palm


def test_the_palm_s_zones_feel_a_block_lying_across_their_rims_as_the_truth_does(scene, hand):
    """The block at rest where the slide begins lies across the palm's edge, its contact points
    clipped to the palm's face on the zones' rim: every one of them counts, so the palm reads the
    block's weight, as the truth's sensors do."""
    from dataclasses import replace

    from inhand_tracker.service.bench.demos import Demo
    from inhand_tracker.service.bench.recorder import record
    from inhand_tracker.sim_backend import Population, PopulationConfig

    obj = catalog_object("block")
    demo = make_allegro_motion(hand, obj, "slide", seconds=8.0)
    demo = replace(demo, controls=demo.controls[:18], phases=())
    truth = record_mujoco(scene, demo, mass=obj.mass, friction=obj.friction)
    pop = Population(robot_spec("allegro_palm"), obj, PopulationConfig(worlds=1, device="cpu"))
    start = Demo("slide", demo.controls, truth.initial_pose[0], truth.initial_q[0], ())
    sim = record(pop, start, np.array([obj.mass]), np.array([obj.friction]))
    settled = slice(8, 17)
    # At rest the palm carries all of the weight (the truth's reading has the sensors' noise).
    assert sim.touch[settled, 0].sum(-1).mean() == pytest.approx(obj.mass * GRAVITY, rel=0.03)
    np.testing.assert_allclose(sim.touch[settled, 0, :2].sum(-1), truth.touch[settled, 0, :2].sum(-1), rtol=0.15)


def test_a_palm_skin_feels_where_the_block_lies_as_the_truth_s_taxels_do():
    """The hand with a 4 x 4 taxel grid on its palm (``allegro_palm_grid``): its scene senses every
    zone; at rest the taxels under the block carry its weight, in the worlds as in the truth, and
    as the fingers push it the pressed taxels change: the palm feels where the block lies."""
    from inhand_tracker.service.bench.demos import Demo
    from inhand_tracker.service.bench.recorder import record
    from inhand_tracker.service.bench.scene_truth import ALLEGRO_PALM_GRID_BLOCK
    from inhand_tracker.sim_backend import Population, PopulationConfig

    grid = Kinematics(robot_spec("allegro_palm_grid"))
    assert len(grid.layout.zone_names) == 28 and grid.layout.zone_names[0] == "G_palm_00"
    assert grid.layout.zone_names[16:] == Kinematics(robot_spec("allegro_palm")).layout.zone_names[2:]
    obj = catalog_object("block")
    scene = load_scene(ALLEGRO_PALM_GRID_BLOCK, grid.layout, obj.mass)
    demo = make_allegro_motion(grid, obj, "push", seconds=8.0)
    truth = record_mujoco(scene, demo, mass=obj.mass, friction=obj.friction)
    taxels = truth.touch[:, 0, :16]
    settled = slice(8, 17)
    assert taxels[settled].sum(-1).mean() == pytest.approx(obj.mass * GRAVITY, rel=0.1)
    pressed = {tuple(np.flatnonzero(t > 0.05)) for t in taxels}
    assert len(pressed) >= 3, pressed  # the block's contact moves across the taxels
    pop = Population(robot_spec("allegro_palm_grid"), obj, PopulationConfig(worlds=1, device="cpu"))
    start = Demo("push", demo.controls[:18], truth.initial_pose[0], truth.initial_q[0], ())
    sim = record(pop, start, np.array([obj.mass]), np.array([obj.friction]))
    # The worlds lean on the same taxels and carry the weight; how it splits among them is each
    # engine's own (box-on-box contact points): 0.41 and 0.22 N where the truth reads 0.30 and 0.33.
    simulated = sim.touch[settled, 0, :16]
    np.testing.assert_array_equal(simulated.mean(0) > 0.1, taxels[settled].mean(0) > 0.1)
    assert simulated.sum(-1).mean() == pytest.approx(obj.mass * GRAVITY, rel=0.03)


def test_a_push_motion_refuses_what_it_cannot_script(hand):
    obj = catalog_object("block")
    with pytest.raises(ValueError, match=r"push motion kind: expected one of .*got 'wave'"):
        make_allegro_motion(hand, obj, "wave")
    with pytest.raises(ValueError, match=r"push motions need the Allegro Hand's joints; robot 'shadow_touch' lacks"):
        make_allegro_motion(Kinematics(robot_spec("shadow_touch")), obj, "push")
    assert SUITES["allegro-palm"].kinds == ALLEGRO_MOTION_KINDS


@pytest.mark.slow
def test_the_short_suite_runs_on_a_cpu(tmp_path):
    out = tmp_path / "out"
    args = ["bench", "accuracy", "--suite", "allegro-palm", "--short", "--methods", "OLP,PBO", "--noise", "med"]
    args += ["--worlds", "8", "--device", "cpu", "--out", str(out), "--cache", str(tmp_path / "cache")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    report = (out / "report.md").read_text()
    assert "allegro-palm-short" in report and "| PBO |" in report


def test_the_cost_ranking_runs_the_suite_s_own_hand_and_ranks_its_touch_zones(tmp_path):
    args = ["bench", "cost-ranking", "--suite", "allegro-palm", "--short", "--method", "REPS", "--worlds", "4"]
    result = CliRunner().invoke(app, [*args, "--device", "cpu", "--cache", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    ranked = json.loads(result.stdout)["objects"]["block"]
    # The suite sends joints and touch zones, no fingertip forces: those terms never vary.
    assert ranked["zone_force"]["defined"] > 0.5 and ranked["force_magnitude"]["rho"] is None, ranked
    assert all(-1 <= r["rho"] <= 1 for r in ranked.values() if r["rho"] is not None), ranked


def test_a_block_resting_on_the_table_beside_the_palm_is_away_and_one_in_the_air_is_not(hand):
    """A hand that carries objects on its palm has left a block that rests on the table and touches
    no link, however near (here 15 cm from the palm, well inside the distance that says "far");
    a block on the palm, or in the air above it or beside it, is still a hypothesis."""
    from inhand_tracker.service.bench.allegro_motions import make_allegro_motion
    from inhand_tracker.sim_backend import HEALTH_AWAY, HEALTH_OK, Population, PopulationConfig

    obj = catalog_object("block")
    demo = make_allegro_motion(hand, obj, "push", seconds=6.0)
    pop = Population(robot_spec("allegro_palm"), obj, PopulationConfig(worlds=4, device="cpu"))
    poses = np.tile(demo.object_pose, (1, 4, 1))
    poses[0, 1, [0, 2]] = poses[0, 1, 0] + 0.15, 0.025  # on the table beside the hand
    poses[0, 2, 2] += 0.03  # in the air above the palm
    poses[0, 3, [0, 2]] = poses[0, 3, 0] + 0.15, 0.10  # falling beside the hand
    pop.reset_state(poses, demo.q)
    pop.set_targets(demo.q[None])
    pop.step()
    assert pop.obs.health[0].tolist() == [HEALTH_OK, HEALTH_AWAY, HEALTH_OK, HEALTH_OK]
    assert pop.config.lost_distance > 0.15
