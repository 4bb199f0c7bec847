"""Section IV-A in small, as CI runs it: the smoke suite of `inhand-tracker bench accuracy` (two
shipped pick-and-place trajectories of the foam brick with hidden mass and friction, medium
initial noise, K=40) as a process, with fixed seeds. The optimizers track better than EYE, and
EYE better than OLP; the report, its JSON and its charts are written."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from inhand_tracker.protocol import TrackState
from inhand_tracker.service.bench import SUITES, AccuracyRun, ground_truth, run_suite
from inhand_tracker.service.bench.report import write_report
from inhand_tracker.service.evaluation import CHI2_6DOF_95
from inhand_tracker.service.paths import DATA_DIR
from inhand_tracker.service.tracker import tracker_config


def test_the_smoke_suite_ships_its_trajectories():
    trajectories = ground_truth(SUITES["smoke"], device="cpu", cache=None)  # found in DATA_DIR, not recorded
    assert [t.name for t in trajectories] == ["foam_brick_pick_place_0", "foam_brick_pick_place_1"]
    assert all((DATA_DIR / f"smoke-{t.name}.traj").exists() and t.truth is not None for t in trajectories)


@pytest.mark.slow
def test_optimizers_beat_eye_and_eye_beats_olp(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "inhand_tracker.service.cli", "bench", "accuracy", "--suite", "smoke", "--noise", "med",
         "--device", "cpu", "--out", str(tmp_path), "--json"],
        capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    summary = json.loads(out.stdout)["summary"]  # Warp is quiet: stdout holds the JSON alone
    add = {m: summary[m]["med"]["mean_mm"] for m in summary}
    print("mean ADD [mm]:", {m: round(v, 2) for m, v in add.items()})  # shown with pytest -s
    for method in ("WRS", "REPS", "PBO"):
        assert add[method] < add["EYE"], add
    assert add["EYE"] < add["OLP"], add
    results = json.loads((tmp_path / "results.json").read_text())
    tracks = results["tracks"]
    assert len(tracks) == 2 * 5 and all(len(t["add_mm"]) == len(t["status"]) == 258 for t in tracks)
    assert {s for t in tracks for s in t["status"]} <= {int(s) for s in TrackState}
    report = (tmp_path / "report.md").read_text()
    assert "| REPS |" in report and "![ADD per method and noise](fig2.png)" in report
    for png in ("fig2.png", "add_foam_brick_pick_place_0.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_repeated_runs_draw_their_own_start_and_report_each_runs_mean(tmp_path):
    # OLP simulates its noisy initial estimate alone with the nominal physics: its ADD is decided
    # by the initial pose drawn, so it shows which start each run got.
    once = run_suite(
        AccuracyRun(SUITES["smoke"], methods=("OLP",), noises=("med",), device="cpu", cache=None, quiet=True)
    )
    thrice = run_suite(AccuracyRun(
        SUITES["smoke"], methods=("OLP",), noises=("med",), device="cpu", cache=None, quiet=True, repeats=3,
        config=tracker_config({"exploration.jitter_bandwidth": 0.5}), frames_to=tmp_path / "frames.npz",
    ))  # fmt: skip
    assert once["tracker"] == {} and thrice["tracker"] == {
        "exploration.jitter_bandwidth": 0.5
    }  # the settings are reported
    assert thrice["repeats"] == 3 and len(thrice["tracks"]) == 3 * len(once["tracks"]) == 6
    first = [t for t in thrice["tracks"] if t["repeat"] == 0]
    # Repeat 0 starts where the single run starts. Later frames differ slightly: a population of
    # another size does not reproduce the physics bit for bit, and the difference grows.
    assert [t["add_mm"][0] for t in first] == [t["add_mm"][0] for t in once["tracks"]]
    starts = {(t["trajectory"], t["repeat"]): t["add_mm"][0] for t in thrice["tracks"]}
    assert len(set(starts.values())) == 6, starts  # every run of every trajectory started elsewhere
    olp = thrice["summary"]["OLP"]["med"]
    assert len(olp["run_means_mm"]) == 3 and np.isclose(np.mean(olp["run_means_mm"]), olp["mean_mm"])
    assert "run_means_mm" not in once["summary"]["OLP"]["med"]
    # One world's cost-weighted mean pose is its pose: both estimates score alike.
    best = thrice["summary_best_world"]["OLP"]["med"]
    assert np.isclose(best["mean_mm"], olp["mean_mm"], rtol=1e-4), (best, olp)
    report = write_report(thrice, tmp_path).read_text()
    runs = " / ".join(f"{m:.2f}" for m in olp["run_means_mm"])
    assert f"| OLP | {olp['mean_mm']:.2f} [{runs}] ± " in report, report
    assert "tracker settings other than the defaults: {'exploration.jitter_bandwidth': 0.5}" in report
    assert "## ADD of the lowest-cost world" in report
    # The saved frames are what each track's coverage was judged on.
    frames = np.load(tmp_path / "frames.npz")
    index = json.loads(str(frames["tracks"]))
    assert [(t["trajectory"], t["repeat"]) for t in index] == [(t["trajectory"], t["repeat"]) for t in thrice["tracks"]]
    for i, track in enumerate(thrice["tracks"]):
        error, covariance = frames[f"{i}/error"].astype(np.float64), frames[f"{i}/covariance"].astype(np.float64)
        assert error.shape == (len(track["add_mm"]), 6) and covariance.shape == (len(track["add_mm"]), 6, 6)
        d2 = np.einsum("fi,fi->f", error, np.linalg.solve(covariance + 1e-10 * np.eye(6), error[..., None])[..., 0])
        assert np.mean(d2 <= CHI2_6DOF_95) == pytest.approx(track["coverage_95"], abs=1e-3)
        assert np.isfinite(frames[f"{i}/cost"]).all() and frames[f"{i}/lost"].shape == error.shape[:1]


def test_bench_accuracy_scores_a_users_own_files(tmp_path):
    """A lab with motion capture scores the tracker on its own recordings: `--files` takes .traj
    files that carry the truth, in place of a suite; one without it is refused."""
    from typer.testing import CliRunner

    from inhand_tracker.protocol import Trajectory
    from inhand_tracker.service.cli import app

    mine = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
    args = ["bench", "accuracy", "--files", str(mine), "--methods", "OLP,PBO", "--noise", "med", "--worlds", "8"]
    result = CliRunner().invoke(app, [*args, "--device", "cpu", "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert results["suite"]["name"] == "files" and results["suite"]["robot"] == "allegro"
    assert {t["trajectory"] for t in results["tracks"]} == {Trajectory.load(mine).name}
    assert results["summary"]["PBO"]["med"]["mean_mm"] < results["summary"]["OLP"]["med"]["mean_mm"]
    blind = Trajectory.load(mine)
    blind.truth = None
    blind.save(tmp_path / "blind.traj")
    result = CliRunner().invoke(app, ["bench", "accuracy", "--files", str(tmp_path / "blind.traj"), "--device", "cpu"])
    assert result.exit_code == 2 and "blind.traj' carries no ground truth" in result.output
