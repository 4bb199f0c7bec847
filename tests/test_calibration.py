"""The robot's model from its own data: `calibrate` fits a robot's servos to its recording and
writes an overlay of its config; the service's model check names a joint whose servo is not the
config's and stays quiet on a robot that matches it."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from inhand_tracker.protocol import OpenSession
from inhand_tracker.service.bench.demos import make_demo
from inhand_tracker.service.bench.excitation import excitation_demo
from inhand_tracker.service.bench.recorder import record
from inhand_tracker.service.cli import app
from inhand_tracker.service.paths import CONFIG_DIR
from inhand_tracker.service.server.config import ServiceConfig
from inhand_tracker.service.server.sessions import SessionManager
from inhand_tracker.sim_backend import (
    HandSpec,
    Kinematics,
    Population,
    PopulationConfig,
    catalog_object,
    load_catalog,
    load_robot,
)

GRIPPER = CONFIG_DIR / "robots" / "example_gripper.toml"
TRUE_KE, TRUE_KD = (300.0, 150.0), (10.0, 20.0)
"""The synthetic robot: the example gripper with its right servo half as stiff and twice as damped
as its config says."""


@pytest.fixture(scope="module")
def gripper_recording(tmp_path_factory) -> tuple[Path, Path]:
    """The synthetic robot's free motion recorded as a .traj without ground truth, and a copy of
    its config to write the overlay beside."""
    folder = tmp_path_factory.mktemp("gripper")
    for f in GRIPPER.parent.glob("example_gripper.*"):
        shutil.copy(f, folder)
    spec, obj = load_robot(GRIPPER), catalog_object("foam_brick")
    demo = excitation_demo(Kinematics(spec), obj, seconds=4.0)
    truth = Population(replace(spec, ke=TRUE_KE, kd=TRUE_KD), obj, PopulationConfig(groups=1, worlds=1, device="cpu"))
    traj = record(truth, demo, np.array([obj.mass]), np.array([obj.friction])).trajectory(0, spec.name, obj.name)
    traj.truth = None  # the robot's own data: commands and measured joints
    traj.save(folder / "free.traj")
    return folder / "free.traj", folder / "example_gripper.toml"


def test_calibrate_recovers_known_gains_of_a_synthetic_robot_and_writes_an_overlay(gripper_recording):
    recording, config = gripper_recording
    args = ["calibrate", str(recording), "--robot", str(config), "--worlds", "24", "--generations", "30"]
    result = CliRunner().invoke(app, [*args, "--device", "cpu", "--json", "--joint-noise", "2e-4"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    fitted = {s: [j[s]["fitted"] for j in summary["joints"]] for s in ("ke", "kd")}
    assert fitted["ke"] == pytest.approx(TRUE_KE, rel=0.1) and fitted["kd"] == pytest.approx(TRUE_KD, rel=0.1), fitted
    right = summary["joints"][1]
    assert right["rms_after"] < 0.2 * right["rms_before"], right
    # The joints' stated noise comes out of the error in quadrature: no model follows it.
    for joint in summary["joints"]:
        assert joint["rms_after_net"] == pytest.approx(np.sqrt(max(joint["rms_after"] ** 2 - 4e-8, 0.0)), abs=1e-7)
    # The overlay extends the config and changes the population built from it.
    overlay = config.with_name("example_gripper.calibrated.toml")
    assert 'extends = "example_gripper.toml"' in overlay.read_text()
    spec = load_robot(overlay)
    assert spec.name == "example_gripper" and dict(spec.servos)["ke"] == pytest.approx(TRUE_KE, rel=0.1)
    pop = Population(spec, catalog_object("foam_brick"), PopulationConfig(groups=1, worlds=2, device="cpu"))
    assert pop.servos("ke")[0, 1].tolist() == pytest.approx(TRUE_KE, rel=0.1)
    report = config.with_name("example_gripper.calibrated.md").read_text()
    assert "| right_slide |" in report and "RMS after, net of noise" in report


def test_calibrate_names_a_bad_setting_and_a_missing_recording(gripper_recording, tmp_path):
    recording, config = gripper_recording
    result = CliRunner().invoke(app, ["calibrate", str(tmp_path / "none.traj"), "--robot", str(config)])
    assert result.exit_code == 4 and "no such recording" in result.output
    noisy = ["calibrate", str(recording), "--robot", str(config), "--joint-noise", "-1", "--device", "cpu"]
    result = CliRunner().invoke(app, noisy)
    assert result.exit_code == 2 and "joint_noise: expected 0 to 1 rad or m, got -1" in result.output
    args = ["calibrate", str(recording), "--robot", str(config), "--settings", "gain", "--device", "cpu"]
    result = CliRunner().invoke(app, args)
    assert (
        result.exit_code == 2
        and "calibrate settings: expected some of ['ke', 'kd', 'effort', 'damping'" in result.output
    )


@pytest.fixture(scope="module")
def pick():
    """A pick and place by the procedural hand, and the hand's index-finger joint it halves."""
    spec, obj = HandSpec(), catalog_object("foam_brick")
    kin = Kinematics(spec)
    demo = make_demo(kin, obj, "pick_place", 0, seconds=6.0, pace=0.7)
    return spec, obj, demo, kin.layout.joint_names.index("index_1")


def _joints_off(spec: HandSpec, truth_spec: HandSpec, obj, demo) -> dict[str, float]:
    truth = Population(truth_spec, obj, PopulationConfig(groups=1, worlds=1, device="cpu"))
    traj = record(truth, demo, np.array([0.03]), np.array([1.0])).trajectory(0, spec.name, obj.name)
    manager = SessionManager(ServiceConfig(groups=1, device="cpu", rate_hz=0), {spec.name: spec}, load_catalog())
    start = {"p0": traj.truth.initial_pose, "q0": traj.truth.initial_q}
    info = manager.open(OpenSession(robot=spec.name, object=obj.name, worlds=32, **start))
    pool = manager.sessions[info.session].pool
    for i in range(traj.frames):
        manager.submit(traj.frame(i, info.session, token=info.token))
        manager.step(pool)
    return manager.status(info.session, info.token).joints_off


def test_the_model_check_names_a_joint_whose_gain_was_halved(pick):
    spec, obj, demo, j = pick
    ke = np.array([spec.wrist_ke] * 6 + [spec.finger_ke] * (len(demo.q) - 6))
    ke[j] *= 0.5
    off = _joints_off(spec, replace(spec, servos=(("ke", tuple(ke)),)), obj, demo)
    assert list(off) == ["index_1"] and off["index_1"] > 0.03, off


def test_the_model_check_stays_quiet_on_a_robot_that_matches_its_config(pick):
    spec, obj, demo, _ = pick
    assert _joints_off(spec, spec, obj, demo) == {}


def test_the_replay_report_names_the_joints_the_model_check_found():
    from inhand_tracker.client.replay import ReplayResult
    from inhand_tracker.client.report import _latency
    from inhand_tracker.protocol import SessionStatus

    counters = dict(frames=90, gaps=0, duplicates=0, late=0, errors=0, latency_p50_ms=5.0, latency_p99_ms=9.0)
    status = SessionStatus(session="s", cost=1.0, spread_m=0.01, joints_off={"robot0:FFJ2": 0.035}, **counters)
    said: list[str] = []
    _latency(ReplayResult([], []), status, said.append)
    assert said[-1].startswith("model check: ") and "robot0:FFJ2 35" in said[-1], said
    said.clear()
    _latency(ReplayResult([], []), status.model_copy(update={"joints_off": {}}), said.append)
    assert not any("model check" in s for s in said)


def test_an_overlay_sets_the_joints_own_damping_armature_and_friction(tmp_path):
    for f in GRIPPER.parent.glob("example_gripper.*"):
        shutil.copy(f, tmp_path)
    overlay = tmp_path / "example_gripper.calibrated.toml"
    servos = "damping = [0.5, 0.25]\narmature = [0.01, 0.02]\nfriction = [0.1, 0.0]\n"
    overlay.write_text(f'extends = "example_gripper.toml"\n\n[servos]\n{servos}')
    pop = Population(load_robot(overlay), catalog_object("foam_brick"), PopulationConfig(worlds=2, device="cpu"))
    for name, values in (("damping", [0.5, 0.25]), ("armature", [0.01, 0.02]), ("friction", [0.1, 0.0])):
        assert pop.servos(name)[0, 1].tolist() == pytest.approx(values), name
    base = Population(load_robot(GRIPPER), catalog_object("foam_brick"), PopulationConfig(worlds=1, device="cpu"))
    assert base.servos("damping")[0, 0].tolist() != pytest.approx([0.5, 0.25])


def test_a_joint_the_fit_leaves_far_off_keeps_the_configs_servo(gripper_recording, monkeypatch):
    from inhand_tracker.protocol import Trajectory
    from inhand_tracker.service.calibration import fit_servos, servos

    recording, config = gripper_recording
    spec, obj = load_robot(config), catalog_object("foam_brick")
    monkeypatch.setattr(servos, "STAYS_OFF", 1e-9)  # every joint as far off as a missing coupling leaves it
    fit = fit_servos(spec, obj, [Trajectory.load(recording)], worlds=8, generations=2, device="cpu")
    assert not fit.identified.any() and fit.fitted["ke"].tolist() == pytest.approx(fit.nominal["ke"].tolist())
    assert (fit.rms_after == fit.rms_before).all() and (fit.rms_fit < fit.rms_before).any()


def test_the_report_names_the_joints_a_fit_leaves_far_off():
    from inhand_tracker.service.calibration import ServoFit
    from inhand_tracker.service.calibration.overlay import calibration_report

    two = np.array([1.0, 1.0])
    fit = ServoFit(
        robot="gripper", joints=("left", "right"), settings=("ke",), nominal={"ke": two}, fitted={"ke": 2 * two},
        spread={"ke": 0.1 * two}, identified=np.array([True, True]), excited=np.array([True, True]),
        rms_before=np.array([0.02, 0.09]), rms_after=np.array([0.005, 0.09]), rms_fit=np.array([0.005, 0.04]),
        worlds=8, generations=2, frames=10, seconds=1.0, device="cpu", joint_noise=0.004,
    )  # fmt: skip
    report = calibration_report(fit)
    assert "more than 15 mrad (mm) off, net of the noise, keep the config's servos: right 40." in report, report
    assert "left 3" not in report


def test_check_settings_pairs_every_setting_with_one_world_and_writes_the_table_it_chose(tmp_path):
    """A lab with motion capture picks its robot's tracker settings from a few grasps: each setting
    tracks them from the same noisy starts as one open-loop world; the overlay it writes carries
    the chosen table, which the robot's config then gives its sessions."""
    from inhand_tracker.service.bench import OWN_SETTINGS
    from inhand_tracker.service.paths import DATA_DIR
    from inhand_tracker.service.tracker.settings import robot_defaults

    config = tmp_path / "my_allegro.toml"
    config.write_text(f'extends = "{(CONFIG_DIR / "robots" / "allegro.toml").as_posix()}"\n')
    traj = str(DATA_DIR / "smoke-foam_brick_pick_place_0.traj")
    args = ["check-settings", traj, "--robot", str(config), "--worlds", "8", "--starts", "2", "--device", "cpu"]
    bad = CliRunner().invoke(app, [*args, "--set", "optimizer.open_loop_ratio=0.5"])
    assert bad.exit_code == 2 and "optimizer.open_loop_ratio: expected 0 (off) or 1 to 10, got 0.5" in bad.output
    result = CliRunner().invoke(app, [*args, "--set", "optimizer.min_separation=4", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "my_allegro.tracker.json").read_text())
    assert summary["robot"] == "allegro" and summary["pairs"] == 2 and summary["method"] == "PBO"
    settings = summary["settings"]
    # The defaults update from the first window: that candidate is the robot's own and is not run twice.
    assert list(settings) == [OWN_SETTINGS, "palm", "until felt", "given"] and settings[OWN_SETTINGS]["table"] == {}
    assert settings["until felt"]["table"] == {"optimizer.until_felt": True}
    assert settings["palm"]["table"] == {"optimizer.open_loop_ratio": 1.5, "optimizer.min_pose_evidence": 10.0}
    assert settings["given"]["table"] == {"optimizer.min_separation": 4.0}
    for s in settings.values():  # each paired with the one world of the same starts
        assert s["mean_mm"] == pytest.approx(summary["one_world_mm"] + s["vs_one_world_mm"], abs=1e-6)
        assert s["upper_mm"] == pytest.approx(s["vs_one_world_mm"] + 1.645 * s["standard_error_mm"], abs=1e-6)
        assert s["within_limit"] == (s["upper_mm"] <= summary["allowance_mm"])
    chosen = summary["chosen"]
    assert settings[chosen]["within_limit"] or not any(s["within_limit"] for s in settings.values())
    overlay = tmp_path / "my_allegro.tracker.toml"
    assert overlay.exists() == (chosen != OWN_SETTINGS)
    assert ("add `tracker = {}` to it" in result.output) == (chosen == OWN_SETTINGS)  # its config gives no table
    if overlay.exists():
        robot = load_robot(overlay)
        assert robot.name == "allegro" and robot_defaults(robot) == settings[chosen]["table"]
    # A recording of another robot is refused, naming both.
    gripper = tmp_path / "gripper.toml"
    gripper.write_text(f'extends = "{GRIPPER.as_posix()}"\n')
    other = CliRunner().invoke(app, ["check-settings", traj, "--robot", str(gripper), "--device", "cpu"])
    assert other.exit_code == 2 and "of robot 'allegro', the config's is 'example_gripper'" in other.output
    from inhand_tracker.protocol import Trajectory

    blind = Trajectory.load(traj)  # a recording without the object's truth: nothing to pair against
    blind.truth = None
    blind.save(tmp_path / "blind.traj")
    untrue = CliRunner().invoke(app, ["check-settings", str(tmp_path / "blind.traj"), "--robot", str(config)])
    assert untrue.exit_code == 2 and "blind.traj' carries no ground truth" in untrue.output


def test_check_settings_keeps_the_robots_own_unless_a_candidate_is_surely_better():
    """The choice: among the settings surely within one world's allowance (the 95 % bound of the
    paired difference, not its mean), the lowest mean; the robot's own stay where a candidate is
    not lower by more than the pairs' standard error; where none is within, the surest."""
    from inhand_tracker.service.bench import OWN_SETTINGS, SettingsCheck

    one = np.full(6, 4e-3)
    check = lambda own, palm: SettingsCheck(  # noqa: E731
        "allegro", "PBO", 40, "cpu", ["t"] * 6, one, {OWN_SETTINGS: np.asarray(own), "palm": np.asarray(palm)},
        {OWN_SETTINGS: {}, "palm": {"optimizer.open_loop_ratio": 1.5}},
    )  # fmt: skip
    spread = 1e-4 * np.array([1.0, -1.0, 2.0, -2.0, 1.5, -1.5])
    assert check(one + 5e-5 + spread, one + 4e-5).chosen() == OWN_SETTINGS  # within, the candidate no surer
    assert check(one - 1e-3, one).chosen() == OWN_SETTINGS  # the robot's own is best
    assert check(one + 3e-3, one + 1e-5).chosen() == "palm"  # the robot's own beyond the allowance
    assert check(one + 1e-4, one - 1e-3 + spread * 0.1).chosen() == "palm"  # the candidate surely better
    # Lower than one world on average, but too spread to be surely within: a few lucky starts.
    lucky = one + 1e-3 * np.array([-4.0, 3.0, -4.0, 3.0, -4.0, 3.0])
    assert not check(lucky, one).within(OWN_SETTINGS) and check(lucky, one).chosen() == "palm"
    assert check(one + 3e-3, one + 2e-3).chosen() == "palm"  # none within: the surest
