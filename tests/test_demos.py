"""The scripted demos in real physics: the hand picks the object up, turns it in the hand by at
least 30 degrees, sets it down and lets go; in the gaiting demo every finger breaks contact and
makes it again while the object stays held."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from inhand_tracker.service.bench.demos import DEMO_KINDS, make_demo
from inhand_tracker.service.bench.recorder import record, sensitivity
from inhand_tracker.sim_backend import Population, PopulationConfig, catalog_object
from inhand_tracker.sim_backend.rotations import quat_conjugate, quat_log, quat_multiply


@pytest.fixture(scope="module")
def recordings(hand):
    spec, kin = hand
    obj = catalog_object("foam_brick")
    demos = [make_demo(kin, obj, kind, 0, seconds=10.0, pace=0.7) for kind in DEMO_KINDS]
    truth = Population(spec, obj, PopulationConfig(groups=2, worlds=1, device="cpu"))
    return demos, record(truth, demos, np.full(2, obj.mass), np.full(2, obj.friction))


def _first(demo, phase: str) -> int:
    return next(i for name, i in demo.phases if name == phase)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    qa, qb = torch.tensor(a[3:], dtype=torch.float64), torch.tensor(b[3:], dtype=torch.float64)
    return float(np.degrees(quat_log(quat_multiply(quat_conjugate(qa), qb)).norm()))


@pytest.mark.parametrize("g", [0, 1], ids=DEMO_KINDS)
def test_pick_turn_in_hand_place_and_let_go(recordings, g):
    demos, rec = recordings
    demo, pose = demos[g], rec.object_pose[:, g]
    rest = rec.initial_pose[g, 2]
    lifted, placed = _first(demo, "carry") - 1, _first(demo, "place") - 1
    turned = next(i for name, i in demo.phases if i > _first(demo, "turn") and name != "turn") - 1
    assert pose[lifted, 2] - rest > 0.05, "lifted with the hand"
    assert _angle_deg(pose[lifted], pose[turned]) >= 30.0, "turned in the hand by at least 30 degrees"
    assert pose[placed, 2] - rest > 0.03, "still held when it is set down"
    assert abs(pose[-1, 2] - rest) < 0.01, "resting on the table at the end"
    assert np.linalg.norm(rec.force[-1, g], axis=-1).max() < 0.2, "let go"
    assert rec.slip[:, g].any() and rec.spin[:, g].any(), "the pads slip"
    assert (np.abs(demo.controls - demo.controls.clip(*_limits(demo))) < 1e-6).all(), "targets within limits"


@pytest.mark.parametrize("g", [0, 1], ids=DEMO_KINDS)
def test_the_pinch_lifts_the_object_where_it_lay(recordings, g):
    """From the first touch to the lift the pads press straight in and the object barely moves.
    Closing the flexion joints past touching swung the thumb's tip up and sideways and shoved it
    16-31 mm over the table: a shove that no tracker can follow from a noisy start."""
    demos, rec = recordings
    touched = np.flatnonzero((np.linalg.norm(rec.force[:, g], axis=-1) > 0.2).any(axis=1))[0]
    lifted = _first(demos[g], "lift")
    pose = rec.object_pose[:, g]
    shove = np.linalg.norm(pose[lifted, :3] - pose[touched - 1, :3])
    assert shove < 0.004, f"the pinch moved the object {shove * 1e3:.1f} mm before the lift"


def _limits(demo):
    from inhand_tracker.sim_backend import HandSpec, Kinematics

    lay = Kinematics(HandSpec()).layout
    return lay.lower, lay.upper


def test_finger_gaiting_breaks_and_makes_contact_finger_by_finger(recordings):
    demos, rec = recordings
    demo = demos[1]
    touching = np.linalg.norm(rec.force[:, 1], axis=-1) > 0.2  # (F, L)
    start = _first(demo, "gait")
    end = next(i for name, i in demo.phases if i > start and name != "gait")
    gait = touching[start:end]
    regrasped = []
    for finger in range(3):  # index, middle, ring; the thumb holds throughout
        released = np.flatnonzero(~gait[:, finger])
        if released.size and gait[released[0] :, finger].any() and gait[: released[0], finger].any():
            regrasped.append(finger)
        if released.size:
            others = np.delete(gait[released], finger, axis=1)
            assert others.sum(axis=1).min() >= 2, f"finger {finger} let go while fewer than two others held"
    # The ring finger's abduction sits at its limit when the object is turned, so it may barely touch.
    assert len(regrasped) >= 2, f"only fingers {regrasped} broke and made contact again"
    assert rec.object_pose[end - 1, 1, 2] - rec.initial_pose[1, 2] > 0.04, "held through the gait"


def test_bad_demo_arguments_name_the_value(hand):
    _, kin = hand
    obj = catalog_object("foam_brick")
    with pytest.raises(ValueError, match=r"demo kind: expected one of .* got .juggle."):
        make_demo(kin, obj, "juggle")
    with pytest.raises(ValueError, match=r"demo pace: expected 0\.2 to 5, got 0\.1"):
        make_demo(kin, obj, pace=0.1)
    with pytest.raises(ValueError, match="has no phase 'dance'"):
        make_demo(kin, obj, seconds=1.0).until("dance")


def test_ground_truth_keeps_only_demos_whose_object_stays_in_the_hand(hand, recordings):
    """A demo whose object slipped out is redone (redrawn) rather than kept: `held` must tell the
    two apart, and `gather` must pick the kept tracks out of the side-by-side draws."""
    spec, _ = hand
    demos, rec = recordings
    assert rec.held(demos).all(), "the nominal brick stays in the hand from the lift to the set-down"
    obj = catalog_object("foam_brick")
    truth = Population(spec, obj, PopulationConfig(groups=2, worlds=1, device="cpu"))
    # The brick lies 8 cm off where the hand reaches: the fingers close on air and it stays put.
    missed = [replace(d, object_pose=d.object_pose + np.float32([0.08, 0, 0, 0, 0, 0, 0])) for d in demos]
    empty = record(truth, missed, np.full(2, obj.mass), np.full(2, obj.friction))
    assert not empty.held(missed).any()
    mixed = type(rec).gather([(empty, 1), (rec, 0)])
    assert mixed.names == (demos[1].name, demos[0].name)
    np.testing.assert_array_equal(mixed.object_pose[:, 0], empty.object_pose[:, 1])
    np.testing.assert_array_equal(mixed.force[:, 1], rec.force[:, 0])
    assert mixed.lengths.tolist() == [demos[1].frames, demos[0].frames]
    assert mixed.held(demos[::-1]).tolist() == [False, True]


def test_a_micrometre_at_the_start_of_the_brick_stays_below_a_millimetre_while_held(hand, recordings):
    """The tracker's millimetres are not lost to chaos in the demo itself. The set-down is another
    matter: a turned box pressed on the table tips one way or the other (2.0 mm from 1 um by the
    end of this short pick and place, up to 40 mm where the thumb turned the brick 50-62 degrees)."""
    spec, _ = hand
    demos, _ = recordings
    obj = catalog_object("foam_brick")
    mass, friction = np.full(2, obj.mass), np.full(2, obj.friction)
    pop = Population(spec, obj, PopulationConfig(groups=4, worlds=1, device="cpu"))
    held = [d.until("place") for d in demos]
    gap = sensitivity(pop, held, mass, friction, shift=1e-6)  # 0.45 mm; 1.05 mm with the re-presses of the gaits
    assert (gap < np.array([1e-3, 2e-3])).all(), f"1 um at the start: {gap * 1e3} mm apart before the set-down"
    # The measure sees a shift that persists: the brick rests 5 mm further along until the grasp.
    assert (sensitivity(pop, held, mass, friction, shift=5e-3) >= 5e-3 - 1e-5).all()
    with pytest.raises(ValueError, match="expected a population of 4 groups"):
        sensitivity(Population(spec, obj, PopulationConfig(groups=2, worlds=1, device="cpu")), demos, mass, friction)


def test_the_banana_pinch_is_not_a_knife_edge(hand):
    """On its back the banana balanced on its curve and the first touch tipped it: 1 um at the start
    became 64 mm by the lift. On its side, pinched at its middle with every pad pressed straight
    in, it ends 0.4-1.4 mm apart (0.003 mm when the flexion joints closed, but that pinch shoved
    the object 16-31 mm over the table)."""
    spec, kin = hand
    obj = catalog_object("toy_banana")
    demos = [make_demo(kin, obj, "pick_place", v).until("carry") for v in range(2)]
    pop = Population(spec, obj, PopulationConfig(groups=4, worlds=1, device="cpu"))
    gap = sensitivity(pop, demos, np.full(2, obj.mass), np.full(2, obj.friction))
    assert (gap < 3e-3).all(), f"1 um at the start moved the lifted banana by {gap * 1e3} mm"
