"""The simulation population on Warp's CPU device: grasps, resampling, graph replay, physics
parameters, observations and errors."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from inhand_tracker.sim_backend import (
    HEALTH_AWAY,
    HEALTH_LOST,
    HEALTH_NAN,
    HEALTH_OK,
    FileRobotSpec,
    Population,
    PopulationConfig,
    catalog_object,
    load_mesh_object,
    load_robot,
    plan_pinch,
)
from inhand_tracker.sim_backend.rotations import quat_rotate

FRAMES_3S = 90
CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _grasped(hand, obj_name: str, worlds: int, **cfg) -> tuple[Population, object]:
    spec, kin = hand
    obj = catalog_object(obj_name)
    grasp = plan_pinch(kin, obj)
    pop = Population(spec, obj, PopulationConfig(worlds=worlds, device="cpu", **cfg))
    pop.reset_state(grasp.object_pose, grasp.q_touch)
    pop.set_targets(np.tile(grasp.q_squeeze, (pop.G, 1)))
    return pop, grasp


@pytest.mark.parametrize("name", ["spam_can", "foam_brick", "toy_banana"])  # the pinched objects
def test_grasp_holds_each_object_for_3_s(hand, name):
    pop, _grasp = _grasped(hand, name, worlds=2)
    for _ in range(10):  # the pads close on the object from touching: it sinks 5-6 mm into them first
        pop.step()
    start = pop.obs.object_pose[..., 2].clone()
    for _ in range(FRAMES_3S):
        pop.step()
    drop = (start - pop.obs.object_pose[..., 2]).max().item()
    assert drop < 0.005, f"{name} dropped {drop * 1e3:.1f} mm in 3 s"
    assert (pop.obs.health == HEALTH_OK).all()
    # Every pad presses on the object: the grasp is a real pinch, not a resting object.
    assert (pop.obs.force.norm(dim=-1) > 0.2).all()


@pytest.mark.parametrize("name", ["foam_brick", "toy_banana"])
def test_mass_writes_the_constants_set_const_would(name):
    """set_params writes the solver's inertial constants of the object itself (no set_const pass);
    they must equal what MuJoCo-Warp's full recomputation gives."""
    import newton
    import warp as wp

    from inhand_tracker.sim_backend import HandSpec

    obj = catalog_object(name)
    pop = Population(HandSpec(), obj, PopulationConfig(groups=2, worlds=2, device="cpu", use_graph=False))
    lo, hi = obj.mass_range
    pop.set_params(mass=torch.tensor([[lo, hi], [0.5 * (lo + hi), obj.mass]]))
    fields = ("body_mass", "body_inertia", "body_subtreemass", "body_invweight0", "dof_invweight0")
    fast = {f: wp.to_torch(getattr(pop.solver.mjw_model, f)).clone() for f in fields}
    pop.solver.notify_model_changed(newton.ModelFlags.BODY_INERTIAL_PROPERTIES)
    for f in fields:
        full = wp.to_torch(getattr(pop.solver.mjw_model, f))
        torch.testing.assert_close(fast[f], full, rtol=1e-6, atol=1e-9, msg=lambda m, f=f: f"{f}: {m}")
    # A resample carries the constants with the mass.
    pop.resample(torch.tensor([[1, 1], [0, 0]]))
    assert torch.equal(pop.params.solver_constants["mass"], pop.mass)


def test_resampled_copies_stay_bit_identical(hand):
    pop, _ = _grasped(hand, "spam_can", worlds=4)
    pop.set_params(mass=torch.tensor([[0.06, 0.1, 0.15, 0.2]]), friction=torch.tensor([[0.5, 0.8, 1.0, 1.4]]))
    wrench = torch.zeros(1, 4, 6)
    wrench[0, :, 1] = torch.tensor([0.5, -0.5, 1.0, 0.0])  # push along y: the worlds diverge
    for _ in range(5):
        pop.set_wrench(wrench)
        pop.step()
    assert not torch.equal(pop.obs.object_pose[0, 0], pop.obs.object_pose[0, 2])
    pop.resample(torch.tensor([[2, 2, 0, 0]]))
    assert pop.mass[0].tolist() == pytest.approx([0.15, 0.15, 0.06, 0.06])
    for _ in range(30):
        pop.step()
        for a, b in ((0, 1), (2, 3)):
            assert torch.equal(pop.obs.object_pose[0, a], pop.obs.object_pose[0, b])
            assert torch.equal(pop.obs.q[0, a], pop.obs.q[0, b])
    for tensor in pop.state_tensors():
        assert torch.equal(tensor[0, 0], tensor[0, 1]) and torch.equal(tensor[0, 2], tensor[0, 3])


def test_worlds_can_take_their_parameters_from_other_worlds_than_their_state(hand):
    pop, _ = _grasped(hand, "spam_can", worlds=3)
    pop.set_params(mass=torch.tensor([[0.06, 0.1, 0.15]]), friction=torch.tensor([[0.5, 0.8, 1.0]]))
    wrench = torch.zeros(1, 3, 6)
    wrench[0, :, 1] = torch.tensor([0.5, -0.5, 1.0])
    pop.set_wrench(wrench)
    for _ in range(3):
        pop.step()
    before = [t.clone() for t in pop.state_tensors()]
    pop.copy_worlds(torch.tensor([[0, 1, 2]]), torch.tensor([[2, 2, 0]]))
    assert pop.mass[0].tolist() == pytest.approx([0.15, 0.15, 0.06])
    assert pop.friction[0].tolist() == pytest.approx([1.0, 1.0, 0.5])
    assert all(torch.equal(a, b) for a, b in zip(before, pop.state_tensors(), strict=True))


def test_a_displaced_object_keeps_what_the_grasp_cannot_see_and_loses_what_it_can(hand):
    """The tracker's roughening: copies of one world, their held object displaced. The pinch
    squeezes along world x, so a shift along x is pushed back by the pads while a turn about x
    (the squeeze axis) is held by friction: the copies stay apart only where the sensors are blind."""
    pop, _ = _grasped(hand, "spam_can", worlds=3)
    for _ in range(15):
        pop.step()
    pop.resample(torch.zeros(1, 3, dtype=torch.int64))
    shift = torch.zeros(1, 3, 6)
    shift[0, 1, 0] = 0.002  # 2 mm along the squeeze
    # 0.05 rad about the squeeze: the plan turns the can's longer side (its x) along world y, so
    # its y lies along the squeeze.
    shift[0, 2, 4] = 0.05
    pop.displace_object(shift)
    for _ in range(30):
        pop.step()
    pose = pop.obs.object_pose[0]
    assert (pop.obs.health == HEALTH_OK).all()
    assert (pop.obs.force.norm(dim=-1) > 0.2).all(), "every displaced copy is still pinched"
    along = abs(pose[1, 0] - pose[0, 0]).item()
    assert along < 0.0005, f"a 2 mm shift along the squeeze stays {along * 1e3:.2f} mm"
    turn = 2 * math.acos(min(1.0, abs(float((pose[2, 3:] * pose[0, 3:]).sum()))))
    assert 0.03 < turn < 0.07, f"a 0.05 rad turn about the squeeze axis became {turn:.3f} rad"
    with pytest.raises(ValueError, match=r"displacement: expected shape \(1, 3, 6\), got \(3, 6\)"):
        pop.displace_object(torch.zeros(3, 6))


def test_an_object_drawn_inside_the_table_is_pushed_out_of_it_before_it_moves(hand):
    """A hypothesis drawn a few millimetres inside what it lies on is moved out along the contact
    normal, keeping its x, y and rotation, instead of being launched by the solver; the worlds not
    asked for are left alone."""
    spec, _ = hand
    obj = catalog_object("foam_brick")
    pop = Population(spec, obj, PopulationConfig(worlds=3, device="cpu"))
    hull = torch.as_tensor(obj.mesh.convex_hull.vertices, dtype=torch.float32)

    def lowest(pose: torch.Tensor) -> torch.Tensor:  # (G, K, 7) -> (G, K) [m]
        q = pose[..., None, 3:].expand(*pose.shape[:-1], len(hull), 4)
        return pose[..., 2] + quat_rotate(q, hull.expand(*pose.shape[:-1], -1, -1))[..., 2].amin(-1)

    rest, tilt = -float(obj.mesh.bounds[0, 2]), [math.sin(0.1), 0.0, 0.0, math.cos(0.1)]
    flat = [0.0, 0.0, 0.0, 1.0]
    pop.reset_state(np.array([[[0.1, 0.0, rest - 0.006, *flat], [0.1, 0.0, rest - 0.006, *flat],
                               [0.1, 0.02, rest - 0.011, *tilt]]]))  # fmt: skip
    before = pop.object_coords.clone()
    assert bool((lowest(before) < -0.005).all())
    pop.separate_object(np.array([[True, False, True]]))
    after = pop.object_coords.clone()
    sunk = lowest(after)[0]
    assert abs(float(sunk[0])) < 2e-4 and abs(float(sunk[2])) < 2e-4, sunk  # on the table, not in it
    assert float(sunk[1]) == pytest.approx(-0.006, abs=1e-6)  # not asked for
    moved = after - before
    assert torch.allclose(moved[..., :2], torch.zeros(1, 3, 2), atol=1e-6), "pushed straight up, off the table"
    assert torch.allclose(moved[..., 3:], torch.zeros(1, 3, 4), atol=1e-6), "rotation kept"
    pop.step()
    speed = torch.linalg.vector_norm(pop.obs.object_pose[0, :, :3] - after[0, :, :3], dim=-1) * pop.config.frame_rate
    assert float(speed[0]) < 0.02 < 0.05 < float(speed[1]), speed  # the solver's push launches the one left inside


def test_graph_replay_equals_eager_stepping(hand):
    pop, _ = _grasped(hand, "foam_brick", worlds=2)
    saved = pop.snapshot()
    for _ in range(5):
        pop.step()
    replayed = [t.clone() for t in pop.state_tensors()]
    obs_replayed = pop.obs.force.clone()
    pop.restore(saved)
    for _ in range(5):
        pop.step_eager()
    for a, b in zip(replayed, pop.state_tensors(), strict=True):
        assert torch.equal(a, b)
    assert torch.equal(obs_replayed, pop.obs.force)


def test_low_friction_slips_where_high_friction_holds(hand):
    pop, _ = _grasped(hand, "spam_can", worlds=2)
    lo, hi = catalog_object("spam_can").friction_range
    pop.set_params(friction=torch.tensor([[lo, hi]]))
    for _ in range(10):
        pop.step()
    start = pop.obs.object_pose[0, :, :3].clone()
    push = torch.zeros(1, 2, 6)
    # The same 6 N downward push on both: more than 0.3 x the ~18 N the pads press with, less
    # than 1.5 x it (10 N moved the high-friction can 14 mm: the pads give as well as slip).
    push[0, :, 2] = -6.0
    slipped = torch.zeros(2)
    for _ in range(10):
        pop.set_wrench(push)
        pop.step()
        slipped += pop.obs.slip[0].amax(dim=-1)
    moved = (pop.obs.object_pose[0, :, :3] - start).norm(dim=-1)
    assert moved[0] > 0.05, f"low friction moved only {moved[0] * 1e3:.1f} mm"
    assert moved[1] < 0.01, f"high friction moved {moved[1] * 1e3:.1f} mm"
    assert slipped[0] > 0, "the slipping world never reported slip"
    assert pop.obs.health[0, 1].item() == HEALTH_OK and (pop.obs.health[0, 0].item() != HEALTH_OK or moved[0] > 0.1)


def test_mass_change_shows_in_the_dynamics(hand):
    pop, _ = _grasped(hand, "spam_can", worlds=2)
    light, heavy = 0.06, 0.18
    pop.set_params(mass=torch.tensor([[light, heavy]]))
    assert pop.mass[0].tolist() == pytest.approx([light, heavy])
    for _ in range(20):
        pop.step()
    # The pads carry the weight: the vertical force of the object on them sums to -m g.
    world_force = quat_rotate(pop.obs.sensor_rot[0], pop.obs.force[0])
    carried = -world_force[..., 2].sum(dim=-1)
    assert carried[0].item() == pytest.approx(light * 9.81, rel=0.35)
    assert carried[1].item() == pytest.approx(heavy * 9.81, rel=0.35)
    # Free in the air below the open hand, the same upward kick lifts the light object 3x as fast.
    pop.reset_state(np.array([0.1, 0.0, 0.12, 0.0, 0.0, 0.0, 1.0]))
    kick = torch.zeros(1, 2, 6)
    kick[0, :, 2] = 3.0  # [N] for one frame
    pop.set_wrench(kick)
    pop.step()
    # n semi-implicit substeps of h under acceleration a travel a h^2 n (n + 1) / 2.
    n, h = pop.config.substeps, pop.config.frame_dt / pop.config.substeps
    accel = torch.tensor([3.0 / light, 3.0 / heavy]) - 9.81
    expected = accel * h * h * n * (n + 1) / 2
    rise = pop.obs.object_pose[0, :, 2] - 0.12
    assert torch.allclose(rise, expected, rtol=0.02), (rise, expected)


def test_observations_have_documented_shapes_and_units(hand):
    _spec, kin = hand
    pop, _ = _grasped(hand, "foam_brick", worlds=3, groups=2)
    for _ in range(10):
        pop.step()
    G, K, D, L = 2, 3, 22, 4
    o = pop.obs
    shapes = {
        "q": (G, K, D),
        "sensor_pos": (G, K, L, 3),
        "sensor_rot": (G, K, L, 4),
        "force": (G, K, L, 3),
        "slip": (G, K, L),
        "slip_dir": (G, K, L, 2),
        "spin": (G, K, L),
        "spin_sense": (G, K, L),
        "object_pose": (G, K, 7),
        "health": (G, K),
    }
    for name, shape in shapes.items():
        assert tuple(getattr(o, name).shape) == shape, name
    assert torch.allclose(o.sensor_rot.norm(dim=-1), torch.ones(G, K, L), atol=1e-5)
    assert torch.allclose(o.object_pose[..., 3:].norm(dim=-1), torch.ones(G, K), atol=1e-5)
    # Sensor poses are forward kinematics of the observed joints, in metres.
    pos, rot = kin.sensor_poses(o.q[0, 0].numpy())
    assert np.allclose(o.sensor_pos[0, 0].numpy(), pos, atol=1e-4)
    assert np.allclose(np.abs((o.sensor_rot[0, 0].numpy() * rot).sum(-1)), 1.0, atol=1e-4)
    # Pad normals (sensor z) point at the object, and the pads push it: force along -z, newtons.
    normal = quat_rotate(o.sensor_rot, torch.tensor([0.0, 0.0, 1.0]).expand(G, K, L, 3))
    to_object = o.object_pose[..., None, :3] - o.sensor_pos
    assert ((normal * to_object).sum(-1) > 0).all()
    assert (o.force[..., 2] < -0.1).all() and (o.force.norm(dim=-1) < 50).all()
    # A slipping pad has a unit slip direction, one that does not slip none.
    length = o.slip_dir.norm(dim=-1)
    assert torch.all((length[o.slip == 1] - 1).abs() < 1e-4) and torch.all(length[o.slip == 0] == 0)
    # Hand at 0.3 m, object held 11 cm below the palm: positions are metres.
    assert o.object_pose[..., 2].mean().item() == pytest.approx(0.19, abs=0.01)


def test_health_marks_away_lost_and_nan_worlds_without_raising(hand):
    pop, grasp = _grasped(hand, "foam_brick", worlds=4)
    poses = np.tile(grasp.object_pose, (1, 4, 1))
    poses[0, 1, :3] = [0.1, 0.4, 0.025]  # on the table, far from the hand
    poses[0, 3, :3] = [0.1, 0.0, -0.2]  # through the table
    pop.reset_state(poses, grasp.q_touch)
    qd = pop.joint_qd
    qd[0, 2, 3] = math.nan  # a world blows up
    pop.step()
    assert pop.obs.health[0].tolist() == [HEALTH_OK, HEALTH_AWAY, HEALTH_NAN, HEALTH_LOST]


def test_bad_inputs_raise_value_errors_naming_the_field(hand, tmp_path):
    _spec, _kin = hand
    pop, _ = _grasped(hand, "foam_brick", worlds=2)
    with pytest.raises(ValueError, match=r"targets: expected shape \(1, 22\), got \(1, 21\)"):
        pop.set_targets(np.zeros((1, 21)))
    bad = np.zeros((1, 22))
    bad[0, 7] = np.nan
    with pytest.raises(ValueError, match=r"targets: 1 non-finite values.*'index_1' = nan"):
        pop.set_targets(bad)
    with pytest.raises(ValueError, match=r"index: expected shape \(1, 2\)"):
        pop.resample(torch.zeros(2, 2, dtype=torch.long))
    with pytest.raises(ValueError, match=r"index: values must lie in \[0, 2\), got min 0 max 5"):
        pop.resample(torch.tensor([[0, 5]]))
    with pytest.raises(ValueError, match=r"mass: 1 values outside \[0.015, 0.05\]"):
        pop.set_params(mass=torch.tensor([[0.02, 3.0]]))
    with pytest.raises(ValueError, match=r"wrench: expected shape \(1, 2, 6\)"):
        pop.set_wrench(torch.zeros(1, 2, 3))
    with pytest.raises(ValueError, match=r"object_pose: expected shape"):
        pop.reset_state(np.zeros(6))
    with pytest.raises(ValueError, match="object: unknown name 'rubber_duck'"):
        catalog_object("rubber_duck")
    garbage = tmp_path / "broken.stl"
    garbage.write_bytes(b"\x00\x01not a mesh at all")
    with pytest.raises(ValueError, match="object 'broken' mesh: "):
        load_mesh_object("broken", str(garbage), mass=0.1, mass_range=(0.05, 0.2))
    with pytest.raises(ValueError, match="no such file"):
        load_mesh_object("missing", str(tmp_path / "missing.obj"), mass=0.1, mass_range=(0.05, 0.2))
    with pytest.raises(ValueError, match="substeps: expected an even number, got 3"):
        PopulationConfig(substeps=3)
    with pytest.raises(ValueError, match="jacobian: expected 'dense' or 'sparse', got 'diagonal'"):
        PopulationConfig(jacobian="diagonal")
    with pytest.raises(ValueError, match="tolerance: expected 0 < tolerance < 1, got 0"):
        PopulationConfig(tolerance=0)
    with pytest.raises(ValueError, match=r"ls_tolerance: expected 0 < ls_tolerance < 1, got 1\.5"):
        PopulationConfig(ls_tolerance=1.5)
    urdf = CONFIGS / "robots" / "example_gripper.urdf"
    assert load_robot(CONFIGS / "robots" / "allegro.toml").finger_ke == 3.0
    bad_cfg = tmp_path / "bad.toml"
    bad_cfg.write_text('kind = "hand"\nfinger_kp = 3.0\n')
    with pytest.raises(ValueError, match=r"unknown keys \['finger_kp'\] for kind 'hand'"):
        load_robot(bad_cfg)
    noisy = tmp_path / "noisy.toml"
    noisy.write_text('kind = "hand"\njoint_noise = 0.005\ntouch_noise = 0.1\ntouch_deadband = 0.2\n')
    spec = load_robot(noisy)
    assert (spec.joint_noise, spec.touch_noise, spec.force_noise, spec.touch_deadband) == (0.005, 0.1, 0.0, 0.2)
    # A [tracker] table: the settings the robot's sessions start from, by dotted name.
    tuned = tmp_path / "tuned.toml"
    tuned.write_text('kind = "hand"\n[tracker]\nupdate_every = 5\n[tracker.optimizer]\nopen_loop_ratio = 1.5\n')
    assert load_robot(tuned).tracker == (("update_every", 5), ("optimizer.open_loop_ratio", 1.5))
    overlay = tmp_path / "overlay.toml"  # an overlay's table replaces its base's
    overlay.write_text('extends = "tuned.toml"\n[tracker.optimizer]\nopen_loop_ratio = 0.0\n')
    assert load_robot(overlay).tracker == (("optimizer.open_loop_ratio", 0.0),)
    tuned.write_text('kind = "hand"\n[tracker]\nupdate_every = [5]\n')
    with pytest.raises(ValueError, match=r"tracker\.update_every: expected a number, flag or name, got \[5\]"):
        load_robot(tuned)
    noisy.write_text('kind = "hand"\nforce_noise = -0.1\n')
    with pytest.raises(ValueError, match=r"robot 'allegro' force_noise: expected >= 0, got -0.1"):
        load_robot(noisy)
    with pytest.raises(ValueError, match=r"joints: \['elbow'\] not in"):
        Population(FileRobotSpec("gripper", str(urdf), ("elbow",), ("left",)), catalog_object("foam_brick"),
                   PopulationConfig(worlds=1, device="cpu"))  # fmt: skip


def test_every_shipped_robot_config_loads_with_settings_the_service_accepts():
    from inhand_tracker.service.tracker.settings import robot_defaults

    tables = {path.stem: robot_defaults(load_robot(path)) for path in sorted((CONFIGS / "robots").glob("*.toml"))}
    assert len(tables) >= 6, tables
    # The palm felt through two halves, or only where the fingertips push the block, follows dead
    # reckoning; the skin overlay does not, nor the Shadow hand's configs.
    palm = {"optimizer.open_loop_ratio": 1.5, "optimizer.min_pose_evidence": 10.0}
    assert tables["allegro_palm"] == palm and tables["allegro_palm_tips"] == palm, tables
    assert tables["allegro_palm_grid"] == tables["shadow_touch"] == tables["shadow_hand"] == {}, tables


def test_the_service_names_a_palm_carrying_robot_whose_config_chose_no_settings(tmp_path, caplog):
    """A robot that carries objects on its palm and whose config gives no [tracker] table runs the
    defaults held open loop until it feels the object, unchecked: the service says so once, naming
    `check-settings`; an empty table is a choice (the defaults) and stays quiet, and every shipped
    palm-carrying config has made one."""
    from inhand_tracker.service.server.admission import Gate
    from inhand_tracker.service.server.budget import FrameTimes
    from inhand_tracker.service.server.config import ServiceConfig
    from inhand_tracker.service.tracker.settings import robot_defaults, unchecked_palms

    shipped = {p.stem: load_robot(p) for p in sorted((CONFIGS / "robots").glob("*.toml"))}
    assert unchecked_palms(shipped) == []
    mine = tmp_path / "my_shadow.toml"
    mine.write_text(f'extends = "{(CONFIGS / "robots" / "shadow_hand.toml").as_posix()}"\n')
    assert load_robot(mine).tracker == ()  # the base's choice carries over
    bare = (CONFIGS / "robots" / "shadow_hand.toml").read_text().replace("tracker = {}\n", "")
    (tmp_path / "shadow_hand.xml").symlink_to(CONFIGS / "robots" / "shadow_hand.xml")
    (tmp_path / "bare.toml").write_text(bare)
    unchecked = load_robot(tmp_path / "bare.toml")
    assert unchecked.tracker is None and robot_defaults(unchecked) == {"optimizer.until_felt": True}
    assert robot_defaults(load_robot(mine)) == {}
    robots = {"shadow_hand": unchecked, "allegro_palm": shipped["allegro_palm"], "gripper": shipped["example_gripper"]}
    assert unchecked_palms(robots) == ["shadow_hand"]
    with caplog.at_level("INFO", logger="inhand_tracker.service.server.admission"):
        Gate(ServiceConfig(), robots, {}, FrameTimes({}), {}, {}, "cpu")
    said = [r.getMessage() for r in caplog.records if "check-settings" in r.getMessage()]
    assert len(said) == 1 and "robot 'shadow_hand' carries objects on its palm" in said[0], said
    assert "until_felt" in said[0], said


DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]


@pytest.mark.parametrize("device", DEVICES)
def test_public_setters_check_values_on_every_device(hand, device):
    """Values already on the device are checked too (the captured graphs use private writers)."""
    spec, _ = hand
    obj = catalog_object("foam_brick")
    pop = Population(spec, obj, PopulationConfig(worlds=2, device=device))
    on = lambda t: t.to(pop.torch_device)  # noqa: E731
    with pytest.raises(ValueError, match=r"mass: 1 values outside \[0.015, 0.05\], e.g. 3"):
        pop.set_params(mass=on(torch.tensor([[0.02, 3.0]])))
    with pytest.raises(ValueError, match=r"friction: 1 values outside .*, e.g. nan"):
        pop.set_params(friction=on(torch.tensor([[0.8, math.nan]])))
    with pytest.raises(ValueError, match=r"index: values must lie in \[0, 2\), got min -1 max 1"):
        pop.resample(on(torch.tensor([[-1, 1]])))
    bad = torch.zeros(1, pop.D)
    bad[0, 3] = math.inf
    with pytest.raises(ValueError, match=r"targets: 1 non-finite values, first at group 0 joint"):
        pop.set_targets(on(bad))
    assert torch.allclose(pop.mass.cpu(), torch.full((1, 2), obj.mass))  # nothing was written
    for setter in (pop.set_params, pop.resample):  # no public way around the checks
        with pytest.raises(TypeError):
            setter(on(torch.tensor([[0, 0]])), check=False)


def test_users_robot_from_urdf_named_in_a_config():
    spec = load_robot(CONFIGS / "robots" / "example_gripper.toml")
    assert isinstance(spec, FileRobotSpec) and spec.joints == ("left_slide", "right_slide")
    pop = Population(spec, catalog_object("foam_brick"), PopulationConfig(worlds=2, device="cpu"))
    pop.reset_state(np.array([0.0, 0.0, 0.025, 0, 0, 0, 1.0]), np.array([0.0, 0.0]))
    pop.set_targets(np.array([[-0.02, 0.02]]))
    for _ in range(3):
        pop.step()
    assert tuple(pop.obs.q.shape) == (1, 2, 2) and tuple(pop.obs.force.shape) == (1, 2, 2, 3)
    # The slides move towards their targets.
    assert pop.obs.q[0, 0, 0] < -0.002 and pop.obs.q[0, 0, 1] > 0.002


def test_the_wrist_slides_along_world_x_y_z_then_turns_yaw_pitch_and_roll():
    """The procedural hand's wrist is one joint of six axes, without links of its own: the palm
    stands at (x, y, z), turned by yaw about world z, pitch about the turned y, the palm's own turn
    (facing the table, fingers along world +x), then roll about the palm's normal; so the model
    has one tree level for the arm, not six."""
    import newton
    from scipy.spatial.transform import Rotation

    from inhand_tracker.sim_backend import HandSpec, add_robot

    builder = newton.ModelBuilder()
    newton.solvers.SolverMuJoCo.register_custom_attributes(builder)
    layout = add_robot(builder, HandSpec())
    model = builder.finalize(device="cpu")
    assert model.body_count == 17 and layout.dof_count == 22  # palm and 16 finger links
    palm = next(b for b in range(model.body_count) if model.body_label[b].endswith("palm"))
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = layout.default_q.copy()
        q[:6] = rng.uniform(-0.5, 0.5, 6) + np.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
        state = model.state()
        joint_q = state.joint_q.numpy()
        joint_q[layout.coord_indices] = q
        state.joint_q.assign(joint_q)
        newton.eval_fk(model, state.joint_q, state.joint_qd, state)
        pose = state.body_q.numpy()[palm]
        turn = Rotation.from_euler("y", 90, degrees=True)
        expected = Rotation.from_euler("ZY", q[3:5]) * turn * Rotation.from_euler("x", q[5])
        np.testing.assert_allclose(pose[:3], q[:3], atol=1e-6)
        assert (expected.inv() * Rotation.from_quat(pose[3:])).magnitude() < 1e-5


def test_shadow_hand_from_its_pypi_package_loads_every_shape_and_feels_what_lies_on_its_palm():
    """A second real hand by files alone: the MJCF that gymnasium-robotics installs, named by
    python:// paths, with its tendons; the object lies on the upturned palm and the curled fingers
    touch it."""
    import newton

    from inhand_tracker.sim_backend import add_robot

    spec = load_robot(CONFIGS / "robots" / "shadow_hand.toml")
    builder = newton.ModelBuilder()
    newton.solvers.SolverMuJoCo.register_custom_attributes(builder)
    layout = add_robot(builder, spec)
    colliders = [s for s in range(builder.shape_count) if builder.shape_flags[s] & newton.ShapeFlags.COLLIDE_SHAPES]
    assert len(colliders) == 22 and layout.dof_count == 24 and layout.sensor_count == 5
    assert all(builder.body_shapes[b] for b in layout.sensor_bodies)

    obj = catalog_object("foam_brick")
    pop = Population(spec, obj, PopulationConfig(worlds=2, device="cpu"))
    pop.reset_state(np.array([0.0, -0.13, 0.18, 0, 0, 0, 1.0]))  # 7 mm above the palm: it falls into place
    fence = layout.default_q.copy()
    for i, name in enumerate(layout.joint_names):  # curl the fingers (the distal joints as their tendon couples them)
        if name[-4:-2] in ("FF", "MF", "RF", "LF") and name[-1] in "012":
            fence[i] = 1.25 if name[-1] == "0" else 1.1
    for _ in range(40):
        pop.set_targets(fence[None])
        pop.step()
    pad = torch.linalg.vector_norm(pop.obs.force[0, 0], dim=-1)  # (L,) [N]
    assert bool((pad[1:3] > 0.05).all()), pad  # the middle and ring fingertips press on the brick
    assert float(pop.object_coords[0, 0, 2]) > 0.15  # still on the palm, not on the table


def test_python_package_paths_and_per_joint_gains_are_checked(tmp_path):
    import newton

    from inhand_tracker.sim_backend import add_robot

    spec = load_robot(CONFIGS / "robots" / "shadow_hand.toml")
    xml = tmp_path / "hand.xml"
    xml.write_text((CONFIGS / "robots" / "shadow_hand.xml").read_text().replace("gymnasium_robotics", "no_such_pkg"))
    with pytest.raises(ValueError, match=r"names the Python package 'no_such_pkg', which is not installed"):
        add_robot(newton.ModelBuilder(), replace(spec, path=str(xml)))
    with pytest.raises(ValueError, match=r"robot 'shadow_hand' ke: expected one value or 24 \(one per joint\), got 3"):
        add_robot(newton.ModelBuilder(), replace(spec, ke=(1.0, 2.0, 3.0)))


def _gripper_with_meshes(root: Path, folder: str, pad_collides: bool = True) -> Path:
    """The example gripper with its pads as mesh files named by ``package://my_gripper/...``, in a
    package folder called ``folder``; returns the URDF's path."""
    import trimesh

    (root / folder / "urdf").mkdir(parents=True)
    (root / folder / "meshes").mkdir()
    trimesh.creation.box(extents=(0.01, 0.03, 0.08)).export(root / folder / "meshes" / "pad.stl")
    urdf = (CONFIGS / "robots" / "example_gripper.urdf").read_text()
    pad = '<geometry><box size="0.01 0.03 0.08"/></geometry>'
    urdf = urdf.replace(pad, '<geometry><mesh filename="package://my_gripper/meshes/pad.stl"/></geometry>')
    if not pad_collides:  # the right pad only seen, never touched
        head, tail = urdf.split('<link name="right">')
        tail = tail.replace("<collision>", "<visual>", 1).replace("</collision>", "</visual>", 1)
        urdf = head + '<link name="right">' + tail
    path = root / folder / "urdf" / "gripper.urdf"
    path.write_text(urdf)
    return path


def _gripper_spec(path: Path, **kw) -> FileRobotSpec:
    return FileRobotSpec(
        "gripper", str(path), joints=("left_slide", "right_slide"), sensor_links=("left", "right"), **kw
    )


def test_package_uris_in_a_urdf_resolve_or_are_refused_with_the_uri(tmp_path):
    import newton

    from inhand_tracker.sim_backend import add_robot

    def shapes_per_link(spec: FileRobotSpec) -> list[int]:
        builder = newton.ModelBuilder()
        layout = add_robot(builder, spec)
        return [len(builder.body_shapes[b]) for b in layout.sensor_bodies]

    # Where the robot's description ships: the package is the folder above urdf/.
    assert shapes_per_link(_gripper_spec(_gripper_with_meshes(tmp_path / "a", "my_gripper"))) == [1, 1]
    # Renamed on disk, it needs package_dirs; without them the file is refused, not loaded without its pads.
    renamed = _gripper_with_meshes(tmp_path / "b", "gripper_v2")
    with pytest.raises(ValueError, match=r"robot 'gripper' path: '.*gripper.urdf' names files that were not found"):
        shapes_per_link(_gripper_spec(renamed))
    packages = tmp_path / "packages"
    (packages / "my_gripper").mkdir(parents=True)
    (renamed.parents[1] / "meshes").rename(packages / "my_gripper" / "meshes")
    assert shapes_per_link(_gripper_spec(renamed, package_dirs=(str(packages),))) == [1, 1]


def test_a_sensor_link_without_a_collision_shape_is_refused_with_the_file_and_link(tmp_path):
    path = _gripper_with_meshes(tmp_path, "my_gripper", pad_collides=False)
    with pytest.raises(ValueError, match=r"sensor_links: 'right' in '.*gripper.urdf' has no collision shape"):
        Population(_gripper_spec(path), catalog_object("foam_brick"), PopulationConfig(worlds=1, device="cpu"))


def test_ramped_targets_move_the_wrist_across_the_frame_from_where_it_stands(hand):
    """A position controller that interpolates reaches a new target only at the frame's end, so
    the wrist moves less within the frame than under a target held as a step; and a target at
    the robot's own joints moves nothing, however it was commanded before the reset."""
    moved = {}
    for ramp in (True, False):
        pop, grasp = _grasped(hand, "foam_brick", worlds=1, ramp_targets=ramp)
        pop.reset_state(grasp.object_pose, grasp.q_touch)
        pop.set_targets(grasp.q_touch[None])
        pop.step()
        assert abs(float(pop.obs.q[0, 0, 0]) - grasp.q_touch[0]) < 1e-4
        target = grasp.q_touch.copy()
        target[0] += 0.02  # wrist x, 2 cm
        pop.set_targets(target[None])
        pop.step()
        moved[ramp] = float(pop.obs.q[0, 0, 0]) - grasp.q_touch[0]
    assert 0.001 < moved[True] < 0.8 * moved[False], moved


def test_the_contact_model_s_precedence_is_defaults_then_the_file_then_the_robot_then_the_user(hand):
    """The defaults (elliptic, impratio 10, implicitfast, Newton's collision) where nobody names one;
    the robot file's own options over them (an MJCF stating none runs MuJoCo's defaults and collides
    as MuJoCo does, as MuJoCo C does); the robot
    config's over the file's; the service's ``[physics]`` or ``--set population.*`` over all."""
    from inhand_tracker.sim_backend import Kinematics
    from inhand_tracker.sim_backend.build import resolve_physics

    spec, _ = hand
    shadow = load_robot(CONFIGS / "robots/shadow_touch.toml")
    assert (shadow.cone, shadow.impratio) == (None, None)  # typed fields of every robot spec: here unset
    layouts = {id(shadow): Kinematics(shadow).layout}

    def resolved(robot, **cfg):
        c = resolve_physics(robot, PopulationConfig(**cfg), layouts.get(id(robot)))
        return c.cone, c.impratio, c.integrator, c.collision

    assert resolved(spec) == ("elliptic", 10.0, "implicitfast", "newton")
    assert resolved(shadow) == ("pyramidal", 1.0, "euler", "mujoco")  # the file's, and its engine's collision
    assert resolved(shadow, impratio=30.0) == ("pyramidal", 30.0, "euler", "mujoco")
    assert resolved(shadow, cone="elliptic", integrator="implicitfast", collision="newton") == (
        "elliptic", 1.0, "implicitfast", "newton"
    )  # fmt: skip
    configured = replace(shadow, impratio=3.0, collision="newton")
    layouts[id(configured)] = layouts[id(shadow)]
    assert resolved(configured) == ("pyramidal", 3.0, "euler", "newton")  # the config over the file
    assert resolved(configured, collision="mujoco")[3] == "mujoco"  # the user over the config
    assert resolved(replace(spec, impratio=2.0), cone="pyramidal") == ("pyramidal", 2.0, "implicitfast", "newton")
    with pytest.raises(ValueError, match="robot 'allegro' cone: expected one of"):
        replace(spec, cone="round")
    with pytest.raises(ValueError, match="robot 'allegro' collision: expected 'mujoco' or 'newton', got 'bullet'"):
        replace(spec, collision="bullet")
    with pytest.raises(ValueError, match=r"population\.collision: expected 'newton' or 'mujoco', got 'bullet'"):
        PopulationConfig(collision="bullet")
    # The worlds' solver runs what the precedence resolved.
    robot = replace(spec, impratio=2.0)
    for cfg, impratio in (({}, 2.0), ({"impratio": 5.0}, 5.0)):
        pop = Population(
            robot, catalog_object("foam_brick"), PopulationConfig(worlds=1, device="cpu", use_graph=False, **cfg)
        )
        assert pop.params.nominal_impratio == pytest.approx(impratio)
