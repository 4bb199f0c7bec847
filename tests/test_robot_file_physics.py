"""The robot file's own physics in every world: its actuators (a joint it leaves unactuated stays
passive, held by its tendon), its options, and the model check that says how far one world follows
a recording and what to change."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest

from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.calibration.model_check import check_model, model_check_report
from inhand_tracker.service.paths import DATA_DIR
from inhand_tracker.sim_backend import (
    FileRobotSpec,
    HandSpec,
    Kinematics,
    Population,
    PopulationConfig,
    catalog_object,
    load_robot,
)
from inhand_tracker.sim_backend.build import resolve_physics

ROOT = Path(__file__).resolve().parents[1]
GRIPPER = ROOT / "tests" / "data" / "tendon_gripper.xml"
FRAMES, RATE, SUBSTEPS = 90, 30.0, 8


def _gripper(**settings) -> FileRobotSpec:
    return FileRobotSpec(
        name="tendon_gripper", path=str(GRIPPER), joints=("prox", "dist", "lift"), sensor_links=("distal",), **settings
    )


def _commands() -> np.ndarray:
    """Three seconds of the proximal joint curling and opening and the lift moving, (F, D)."""
    t = np.arange(FRAMES) / RATE
    prox = 0.6 + 0.5 * np.sin(2 * np.pi * 0.5 * t)
    lift = 0.03 * np.sin(2 * np.pi * 0.4 * t)
    return np.stack([prox, 1.14 * prox, lift], axis=1).astype(np.float32)  # a target for dist is ignored


def _mujoco_c(commands: np.ndarray) -> np.ndarray:
    """The file in MuJoCo C, its actuators' targets moved across each frame, joints per frame (F, D)."""
    model = mujoco.MjModel.from_xml_path(str(GRIPPER))
    data = mujoco.MjData(model)
    steps = round(1.0 / (RATE * model.opt.timestep))
    model.opt.timestep = 1.0 / (RATE * steps)
    qpos = [model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in ("prox", "dist", "lift")]
    driven = [int(model.actuator_trnid[a, 0]) for a in range(model.nu)]  # each actuator's joint
    column = [("prox", "dist", "lift").index(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)) for j in driven]
    data.ctrl[:] = 0.0
    mujoco.mj_forward(model, data)
    last, out = np.zeros(3), []
    for u in commands.astype(np.float64):
        for i in range(steps):
            data.ctrl[:] = (last + (i + 1) / steps * (u - last))[column]
            mujoco.mj_step(model, data)
        last = u
        out.append(data.qpos[qpos].copy())
    return np.asarray(out)


def _worlds(spec: FileRobotSpec, commands: np.ndarray) -> np.ndarray:
    """One world of ``spec`` replaying ``commands``, its joints per frame (F, D)."""
    cfg = PopulationConfig(worlds=1, device="cpu", substeps=SUBSTEPS, frame_rate=RATE)
    pop = Population(spec, catalog_object("block"), cfg)
    pop.reset_state(np.array([1.0, 1.0, 0.03, 0, 0, 0, 1.0]), np.zeros(3))  # the object far from the gripper
    out = []
    for u in commands:
        pop.set_targets(u[None])
        pop.step()
        out.append(pop.obs.q[0, 0].cpu().numpy().astype(np.float64))
    return np.asarray(out)


def test_an_unactuated_joint_tied_by_a_tendon_follows_as_mujoco_c_has_it():
    spec = _gripper()
    layout = Kinematics(spec).layout
    assert layout.actuated.tolist() == [True, False, True]  # the file drives prox and lift, not dist
    pop = Population(spec, catalog_object("block"), PopulationConfig(worlds=1, device="cpu", use_graph=False))
    ke, kd, effort = (pop.servos(s)[0, 0].numpy() for s in ("ke", "kd", "effort"))
    assert (
        np.allclose(ke, [0.8, 0.0, 200.0])
        and np.allclose(kd, [0.0, 0.0, 5.0])
        and np.allclose(effort[[0, 2]], [0.5, 50.0])
    )
    commands = _commands()
    truth, worlds = _mujoco_c(commands), _worlds(spec, commands)
    assert np.ptp(truth[:, 1]) > 0.5  # the distal joint moved, through the tendon only
    rms = np.sqrt(np.mean((worlds - truth) ** 2, axis=0))
    assert (rms < 0.005).all(), rms


def test_a_config_s_servos_replace_the_file_s_on_driven_joints_and_never_drive_a_passive_one():
    pop = Population(
        _gripper(ke=2.0, kd=0.1), catalog_object("block"), PopulationConfig(worlds=1, device="cpu", use_graph=False)
    )
    ke, kd = (pop.servos(s)[0, 0].numpy() for s in ("ke", "kd"))
    assert np.allclose(ke, [2.0, 0.0, 2.0]) and np.allclose(kd, [0.1, 0.0, 0.1])


def test_every_shipped_file_robot_runs_its_file_s_actuators_and_contact_model():
    shadow = load_robot(ROOT / "configs/robots/shadow_hand.toml")
    layout = Kinematics(shadow).layout
    passive = [n.rsplit(":", 1)[-1] for n, a in zip(layout.joint_names, layout.actuated, strict=True) if not a]
    assert passive == ["FFJ0", "MFJ0", "RFJ0", "LFJ0"]
    for name in ("shadow_hand", "shadow_touch", "allegro_palm", "allegro_palm_grid"):
        robot = load_robot(ROOT / f"configs/robots/{name}.toml")
        physics = resolve_physics(robot, PopulationConfig(), Kinematics(robot).layout)
        # The files state no <option>: MuJoCo's defaults and its own collision, as MuJoCo C runs them.
        assert (physics.cone, physics.impratio, physics.integrator, physics.collision) == (
            "pyramidal", 1.0, "euler", "mujoco"
        ), name  # fmt: skip


@pytest.mark.slow
def test_check_model_names_a_halved_actuator_and_a_wrong_cone():
    """The bundled pick and place was recorded by the procedural hand as configured (elliptic
    cone); checked against a config that says pyramidal, and one whose index finger's middle
    joint has twice the servo, the check names each and says what to change."""
    whole = Trajectory.load(DATA_DIR / "smoke-foam_brick_pick_place_0.traj")
    sensing = {k: v[:150] for k, v in whole.sensing.items() if v is not None}
    truth = replace(whole.truth, pose=whole.truth.pose[:150])
    traj = Trajectory(whole.name, whole.robot, whole.object, whole.frame_rate, truth=truth, **sensing)
    hand = HandSpec()
    fine = check_model(hand, [traj], device="cpu", variants=False)
    assert np.max(fine.net(fine.base.joint_rms)) < 0.002 and np.mean(fine.base.drift) < 0.002
    wrong_cone = check_model(replace(hand, cone="pyramidal"), [traj], device="cpu")
    assert wrong_cone.changes()[0][0] == "cone elliptic", model_check_report(wrong_cone)
    names = Kinematics(hand).layout.joint_names
    j = names.index(next(n for n in names if n.endswith("index_1")))
    probe = Population(hand, catalog_object(traj.object), PopulationConfig(worlds=1, device="cpu", use_graph=False))
    ke = probe.servos("ke")[0, 0].numpy().astype(np.float64)
    ke[j] *= 2.0  # the config says twice the servo the recording's hand had: the truth's is half the config's
    strong = check_model(replace(hand, servos=(("ke", tuple(ke)),)), [traj], device="cpu")
    report = model_check_report(strong)
    assert strong.changes()[0][0] == f"servo {names[j]} x0.5", report
    assert names[j] in report.split("mismatches:")[1]


def test_check_model_on_the_command_line_reports_every_joint_or_names_what_is_missing(tmp_path):
    from typer.testing import CliRunner

    from inhand_tracker.service.cli import app

    robot, traj = str(ROOT / "configs/robots/allegro.toml"), str(DATA_DIR / "smoke-foam_brick_pick_place_0.traj")
    missing = CliRunner().invoke(app, ["check-model", str(tmp_path / "none.traj"), "--robot", robot, "--device", "cpu"])
    assert missing.exit_code == 4 and "check-model: no such recording" in missing.output
    bad = CliRunner().invoke(
        app, ["check-model", traj, "--robot", robot, "--device", "cpu", "--set", "population.cone=round"]
    )
    assert bad.exit_code == 2 and "population.cone: expected 'pyramidal' or 'elliptic'" in bad.output, bad.output
    out = CliRunner().invoke(app, ["check-model", traj, "--robot", robot, "--device", "cpu", "--no-variants"])
    assert out.exit_code == 0, out.output
    names = Kinematics(HandSpec()).layout.joint_names
    assert all(f"| {n} | yes |" in out.output for n in names) and "mismatches: none" in out.output, out.output
