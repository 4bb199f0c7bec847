"""Ground truth from another engine: the robot written as MJCF and run in MuJoCo C, and the
cross-engine suite in short form through the command line."""

from __future__ import annotations

import json
import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from typer.testing import CliRunner

from inhand_tracker.protocol import SENSING
from inhand_tracker.service.bench.motions import MOTION_KINDS, make_motion
from inhand_tracker.service.bench.mujoco_truth import export_scene, record_mujoco
from inhand_tracker.service.bench.shadow_motions import DISTAL_COUPLING, SHADOW_MOTION_KINDS, make_shadow_motion
from inhand_tracker.service.bench.suites import robot_spec
from inhand_tracker.service.cli import app
from inhand_tracker.sim_backend import HandSpec, Kinematics, catalog_object


def test_mujoco_truth_lifts_the_object_and_senses_it_as_the_tracker_would(tmp_path):
    obj = catalog_object("foam_brick")
    scene = export_scene(HandSpec(), obj, tmp_path / "hand.xml")
    assert (tmp_path / "hand.xml").read_text().startswith("<mujoco")
    assert scene.model.opt.timestep <= 0.001
    demo = make_motion(Kinematics(HandSpec()), obj, MOTION_KINDS[0], seconds=8.0)
    rec = record_mujoco(scene, demo, mass=obj.mass, friction=obj.friction)
    assert rec.held([demo])[0]
    d, l = demo.controls.shape[1], len(scene.sensor_bodies)
    for f in SENSING:
        assert rec.sensing[f.name].shape == (demo.frames, 1, *f.shape(d, l)), f.name
    first = dict(reversed(demo.phases))
    carry = slice(first["carry"], first["place"])
    touching = np.linalg.norm(rec.force[carry, 0], axis=-1) > 0.1  # (F, L)
    assert touching.all(axis=-1).mean() > 0.9  # all four pads hold it through the carry
    # The pads press inward: the object's force on each pad points out of it, along -z.
    assert (rec.force[carry, 0, :, 2] < 0).mean() > 0.9
    # Joints follow their targets: the wrist's slides within 5 mm once settled.
    assert np.abs(rec.q[carry, 0, :3] - demo.controls[carry, :3]).max() < 0.005
    # The same hidden physics gives the same track (MuJoCo C on the CPU is deterministic).
    again = record_mujoco(scene, demo, mass=obj.mass, friction=obj.friction)
    assert np.array_equal(again.object_pose, rec.object_pose)


def test_cross_engine_suite_in_short_form_tracks_better_than_open_loop(tmp_path):
    out = tmp_path / "out"
    args = ["bench", "accuracy", "--suite", "cross-engine", "--short", "--methods", "OLP,PBO", "--noise", "med"]
    args += ["--device", "cpu", "--out", str(out), "--cache", str(tmp_path / "cache")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    results = json.loads((out / "results.json").read_text())
    assert results["suite"]["engine"] == "mujoco" and results["suite"]["name"] == "cross-engine-short"
    summary = {m: results["summary"][m]["med"]["mean_mm"] for m in ("OLP", "PBO")}
    assert summary["PBO"] < summary["OLP"], summary
    assert all(np.isfinite(t["open_loop_mean_mm"]) for t in results["tracks"])
    report = (out / "report.md").read_text()
    assert "MuJoCo C" in report and "| trajectory | open loop |" in report
    assert sorted(p.name for p in (tmp_path / "cache").glob("*.traj")) == [
        f"cross-engine-short-spam_can_{k}_0.traj" for k in sorted(MOTION_KINDS[:2])
    ]


def test_mujoco_truth_on_the_shadow_hand_keeps_the_object_on_its_palm_and_feels_it(tmp_path):
    """The second hand, from its package's MJCF with its tendons: each palm motion keeps the can on
    the hand, the fingertips touch it, and the distal joints follow their middle ones."""
    spec, obj = robot_spec("shadow_hand"), catalog_object("spam_can")
    scene = export_scene(spec, obj, tmp_path / "shadow.xml")
    kin = Kinematics(spec)
    names = [n.rsplit(":", 1)[-1] for n in kin.layout.joint_names]
    middle, distal = names.index("MFJ1"), names.index("MFJ0")
    for kind in SHADOW_MOTION_KINDS:
        demo = make_shadow_motion(kin, obj, kind, seconds=8.0)
        rec = record_mujoco(scene, demo, mass=obj.mass, friction=obj.friction)
        assert rec.held([demo], margin=-0.03)[0], kind
        first = dict(reversed(demo.phases))
        carry = slice(first["carry"], first["place"])
        touching = (np.linalg.norm(rec.force[carry, 0], axis=-1) > 0.05).any(axis=-1)
        assert touching.mean() > 0.3, (kind, touching.mean())
        coupled = rec.q[carry, 0, distal] - DISTAL_COUPLING * rec.q[carry, 0, middle]
        assert np.abs(coupled).max() < 0.2, kind  # the tendon's slack: +-1 mm, 0.14 rad of the distal joint


def test_the_shadow_hands_truth_in_the_trackers_own_physics_keeps_the_object_on_its_palm(tmp_path, caplog):
    """The Shadow Hand's palm motions in Newton keep the object on the palm and touching it; two runs
    started side by side record the truth once and score the same one (a GPU's recordings differ)."""
    from inhand_tracker.service.bench.suites import SUITES
    from inhand_tracker.service.bench.truth import ground_truth

    suite = SUITES["paper-shadow"].short()
    with caplog.at_level(logging.INFO), ThreadPoolExecutor(2) as pool:
        tracks, other = pool.map(lambda _: ground_truth(suite, device="cpu", cache=tmp_path), range(2))
    assert sum(r.getMessage().startswith("recording ground truth") for r in caplog.records) == 1
    assert all(np.array_equal(a.truth.pose, b.truth.pose) for a, b in zip(tracks, other, strict=True))
    assert [t.robot for t in tracks] == ["shadow_hand"] * 2 and tracks[0].meta["engine"] == "newton"
    for t in tracks:
        assert t.truth.pose[:, 2].min() > 0.14, t.name  # on the palm (its face is 14.7 cm up), not the table
        assert (np.linalg.norm(t.force, axis=-1) > 0.05).any(-1).mean() > 0.3, t.name


@pytest.mark.slow
def test_cross_engine_suite_on_the_shadow_hand_in_short_form(tmp_path):
    out = tmp_path / "out"
    args = ["bench", "accuracy", "--suite", "cross-engine-shadow", "--short", "--methods", "OLP,PBO"]
    args += ["--noise", "med", "--device", "cpu", "--out", str(out), "--cache", str(tmp_path / "cache")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    results = json.loads((out / "results.json").read_text())
    assert results["suite"]["name"] == "cross-engine-shadow-short"
    summary = {m: results["summary"][m]["med"]["mean_mm"] for m in ("OLP", "PBO")}
    # The object stays tracked on the palm (about 9-11 mm here, one start; PBO below OLP is a claim
    # over many starts, for the GPU benchmark): a hypothesis thrown off the hand costs 100 mm or more.
    assert max(summary.values()) < 20.0, summary
    assert all(np.isfinite(t["open_loop_mean_mm"]) for t in results["tracks"])
    assert sorted(p.name for p in (tmp_path / "cache").glob("*.traj")) == [
        f"cross-engine-shadow-short-spam_can_{k}_0.traj" for k in sorted(SHADOW_MOTION_KINDS[:2])
    ]


def test_rank_correlation_is_spearmans_rho_per_group_and_term():
    from scipy.stats import spearmanr

    from inhand_tracker.service.bench.ranking import rank_correlation

    rng = np.random.default_rng(0)
    error = rng.random((3, 40))
    cost = np.stack([error * 2.0, -error, rng.random((3, 40)), np.ones((3, 40))], axis=-1)
    cost[1, :5, 2] = cost[1, 5, 2]  # ties take their mean rank, as scipy's
    rho = rank_correlation(cost, error)
    assert rho.shape == (3, 4)
    assert np.allclose(rho[:, 0], 1.0) and np.allclose(rho[:, 1], -1.0)
    assert np.allclose(rho[:, 2], [spearmanr(cost[g, :, 2], error[g]).statistic for g in range(3)])
    assert np.isnan(rho[:, 3]).all()  # a term that does not vary ranks nothing
