"""Section IV-A in small, as CI runs it: the smoke suite of `inhand-tracker bench accuracy` (two
shipped pick-and-place trajectories of the foam brick with hidden mass and friction, medium
initial noise, K=40) as a process, with fixed seeds. The optimizers track better than EYE, and
EYE better than OLP; the report, its JSON and its charts are written."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from service.accuracy import DATA_DIR, SUITES, ground_truth


def test_the_smoke_suite_ships_its_trajectories():
    trajectories = ground_truth(SUITES["smoke"], device="cpu", cache=None)  # found in DATA_DIR, not recorded
    assert [t.name for t in trajectories] == ["foam_brick_pick_place_0", "foam_brick_pick_place_1"]
    assert all((DATA_DIR / f"smoke-{t.name}.traj").exists() and t.truth is not None for t in trajectories)


@pytest.mark.slow
def test_optimizers_beat_eye_and_eye_beats_olp(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "service.cli", "bench", "accuracy", "--suite", "smoke", "--noise", "med",
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
    assert len(results["tracks"]) == 2 * 5 and all(len(t["add_mm"]) == 258 for t in results["tracks"])
    report = (tmp_path / "report.md").read_text()
    assert "| REPS |" in report and "![ADD per method and noise](fig2.png)" in report
    for png in ("fig2.png", "add_foam_brick_pick_place_0.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
