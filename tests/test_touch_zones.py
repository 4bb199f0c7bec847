"""Touch zones: a scalar normal force per region of a link (touch arrays, pressure pads, taxel
skins) declared in the robot config, simulated in every world, sent by the robot, compared by the
cost; and the recovery that reads them (an object the palm feels has not fallen)."""

from __future__ import annotations

import numpy as np
import pytest

from inhand_tracker.protocol import OpenSession, TrackState
from inhand_tracker.service.bench.demos import make_demo
from inhand_tracker.service.bench.recorder import record
from inhand_tracker.service.evaluation import add_error
from inhand_tracker.service.server.config import ServiceConfig
from inhand_tracker.service.server.sessions import ServiceError, SessionManager
from inhand_tracker.service.tracker import TrackerConfig
from inhand_tracker.service.tracker.layout import GroupEstimates
from inhand_tracker.service.tracker.recovery import Recovery
from inhand_tracker.sim_backend import (
    HandSpec,
    Kinematics,
    Population,
    PopulationConfig,
    catalog_object,
    load_catalog,
    load_robot,
)
from inhand_tracker.sim_backend.robots import TouchZone

OBJECT = "foam_brick"
_PADS = tuple(TouchZone(f"{f}_pad", f"{f}_link3", (0, 0, 0.0267), (0.013, 0.013, 0.013)) for f in ("index", "middle"))
ZONES = (TouchZone("palm", "palm", (0, 0, 0), (0.03, 0.06, 0.05)), *_PADS,
         TouchZone("thumb_pad", "thumb_link3", (0, 0, 0.0423), (0.013, 0.013, 0.013)))  # fmt: skip
SPEC = HandSpec(name="allegro_skin", touch_zones=ZONES)


@pytest.fixture(scope="module")
def trajectory():
    """A pick and place by a hand with four touch zones, recorded in the tracker's own physics."""
    obj = catalog_object(OBJECT)
    truth = Population(SPEC, obj, PopulationConfig(groups=1, worlds=1, device="cpu"))
    demo = make_demo(Kinematics(SPEC), obj, "pick_place", 0, seconds=6.0, pace=0.7)
    return record(truth, demo, np.array([0.03]), np.array([1.0])).trajectory(0, SPEC.name, OBJECT)


def _manager() -> SessionManager:
    return SessionManager(ServiceConfig(groups=1, device="cpu", rate_hz=0), {SPEC.name: SPEC}, load_catalog())


def test_the_simulated_zones_feel_what_the_fingertips_feel(trajectory):
    touch, force = trajectory.sensing["touch"], np.linalg.norm(trajectory.sensing["force"], axis=-1)
    assert touch.shape == (trajectory.frames, len(ZONES))
    held = force[:, 0] > 1.0  # the index pad presses the brick
    assert held.sum() > 30
    # The index pad's zone reads the normal part of the index sensor's force: a little less, never more.
    ratio = touch[held, 1] / force[held, 0]
    assert np.all(ratio <= 1.0 + 1e-3) and np.median(ratio) > 0.8, ratio
    assert touch[~(force > 0).any(-1)].max() == 0.0, "nothing touches, no zone feels"


def test_a_robot_config_declares_its_zones_and_a_wrong_link_is_named(tmp_path):
    config = tmp_path / "skin.toml"
    config.write_text(
        'kind = "hand"\nname = "skin"\n[[touch_zones]]\nname = "palm"\nlink = "palm"\n'
        "center = [0.0, 0.0, 0.0]\nhalf_extents = [0.03, 0.06, 0.05]\n"
    )
    spec = load_robot(config)
    assert spec.touch_zones == (TouchZone("palm", "palm", (0.0, 0.0, 0.0), (0.03, 0.06, 0.05)),)
    assert Kinematics(spec).layout.zone_names == ("palm",)
    with pytest.raises(ValueError, match=r"robot 'skin' touch_zones: links \[\('palm', 'wrist_link'\)\] not in"):
        Kinematics(HandSpec(name="skin", touch_zones=(TouchZone("palm", "wrist_link"),)))


def test_a_frame_of_the_wrong_zone_count_is_refused_naming_the_field(trajectory):
    manager = _manager()
    info = manager.open(OpenSession(robot=SPEC.name, object=OBJECT, p0=trajectory.truth.initial_pose, worlds=2))
    assert info.zone_names == ["palm", "index_pad", "middle_pad", "thumb_pad"]
    frame = trajectory.frame(0, info.session, token=info.token)
    with pytest.raises(ServiceError, match=r"RobotFrame.touch: expected shape \(4,\), got \(3,\)"):
        manager.submit(frame.model_copy(update={"touch": np.zeros(3, np.float32)}))
    manager.submit(frame)  # the session goes on
    assert manager.status(info.session, info.token).errors == 1


def test_a_session_sending_touch_zones_only_tracks(trajectory):
    """No fingertip forces, no slip: joints and touch zones alone."""
    manager = _manager()
    start = trajectory.truth.initial_pose.copy()
    start[:3] += 0.004  # a noisy start
    info = manager.open(
        OpenSession(robot=SPEC.name, object=OBJECT, p0=start, q0=trajectory.truth.initial_q, worlds=8, method="PBO")
    )
    pool = manager.sessions[info.session].pool
    untouched = {"force": None, "slip": None, "slip_dir": None, "spin": None, "spin_sense": None}
    points, errors, zone_terms = catalog_object(OBJECT).surface_points(500), [], 0.0
    for i in range(trajectory.frames):
        manager.submit(trajectory.frame(i, info.session, token=info.token).model_copy(update=untouched))
        (estimate,) = manager.step(pool)
        errors.append(add_error(points, trajectory.truth.pose[i], estimate.pose))
        terms = pool.tracker.cost.last_terms[0]
        assert float(terms[:, 3:10].abs().max()) == 0.0, "fingertip and slip terms drop out: the frame lacks them"
        zone_terms += float(terms[:, 10:].sum())
    assert zone_terms > 0, "the zones' terms score the worlds"
    assert np.mean(errors) < 0.01, f"mean ADD {np.mean(errors) * 1e3:.1f} mm"
    assert manager.status(info.session, info.token).errors == 0


def test_recovery_does_not_lay_an_object_the_palm_feels_on_the_table():
    """Every world lost the object: where the robot's palm still feels it, the re-seed stays in the
    hand (around the last trusted pose); only where no sensor of the hand feels anything did it fall."""
    pose = np.tile(np.array([0.1, 0.0, 0.15, 0, 0, 0, 1], np.float32), (2, 1))
    recovery = Recovery(TrackerConfig(), groups=2, sensors=4, moment=np.eye(3) * 1e-3, falls=True)
    recovery.start(pose, np.ones(2, bool))
    est = GroupEstimates(frame=1, pose=pose, best_pose=pose, cost=np.ones(2), mean_pose=pose,
                         covariance=np.tile(np.eye(6) * 1e-8, (2, 1, 1)), mass=np.ones(2), friction=np.ones(2),
                         lost=np.ones(2), contact_disagreement=np.zeros(2), status=np.zeros(2, np.int64),
                         mode_weights=np.array([[1.0, 0.0]] * 2))  # fmt: skip
    touch = np.array([[2.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]], np.float32)  # group 0's palm is pressed
    both = np.ones(2, bool)
    reseeds = recovery.watch(est, np.zeros((2, 4, 3), np.float32), both, np.zeros((2, 3)), touch, both)
    assert (recovery.status == TrackState.DIVERGED).all()
    on_table = {bool(r.on_table): np.flatnonzero(r.groups).tolist() for r in reseeds}
    assert on_table == {False: [0], True: [1]}, on_table
    held = next(r for r in reseeds if not r.on_table)
    assert held.anchor[0, 2] == pytest.approx(0.15), "re-seeded where the palm holds it, not below"
