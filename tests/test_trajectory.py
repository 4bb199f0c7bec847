"""Trajectory files: what the protocol carries plus the ground truth, versioned, read back exactly;
bad files are refused with the file and the reason. Also the per-group settings a batched suite
relies on, and the PNG charts of the report."""

from __future__ import annotations

from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch

from inhand_tracker.protocol import TRAJECTORY_VERSION, GroundTruth, RobotFrame, Trajectory
from inhand_tracker.service.bench.plots import bar_chart, line_chart, xy_chart
from inhand_tracker.service.paths import DATA_DIR
from inhand_tracker.service.tracker.optimizers import OptimizerConfig, update


def _trajectory(frames: int = 5, force: bool = True) -> Trajectory:
    rng = np.random.default_rng(0)
    f32 = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    truth = GroundTruth(initial_pose=np.array([0, 0, 0.1, 0, 0, 0, 1], np.float32), initial_q=f32(22),
                        pose=f32(frames, 7), mass=0.03, friction=0.9)  # fmt: skip
    return Trajectory(name="t", robot="allegro", object="foam_brick", frame_rate=30.0, controls=f32(frames, 22),
                      q=f32(frames, 22), force=f32(frames, 4, 3) if force else None, truth=truth,
                      meta={"demo": "x", "variant": 1})  # fmt: skip


def test_round_trip_is_exact(tmp_path):
    a = _trajectory(force=False)
    b = Trajectory.load(a.save(tmp_path / "a.traj"))
    assert (b.name, b.robot, b.object, b.frame_rate, b.meta) == (a.name, a.robot, a.object, 30.0, a.meta)
    for name in ("controls", "q", "stamp"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert b.force is None and b.slip is None
    assert np.array_equal(a.truth.pose, b.truth.pose) and b.truth.mass == pytest.approx(0.03)


def test_rows_are_robot_frames():
    t = _trajectory()
    frame = t.frame(3, session="s1")
    assert isinstance(frame, RobotFrame) and frame.seq == 3 and frame.stamp == pytest.approx(0.1)
    assert np.array_equal(frame.force, t.force[3]) and frame.slip is None


def test_bad_files_are_refused_with_the_reason(tmp_path):
    path = _trajectory().save(tmp_path / "a.traj")
    doc = msgpack.unpackb(path.read_bytes(), raw=False)
    doc["version"] = TRAJECTORY_VERSION + 1
    path.write_bytes(msgpack.packb(doc, use_bin_type=True))
    with pytest.raises(ValueError, match=f"trajectory format v{TRAJECTORY_VERSION + 1}, this reader reads v1"):
        Trajectory.load(path)
    (tmp_path / "junk.traj").write_bytes(b"\xc1\x00junk")
    with pytest.raises(ValueError, match=r"junk\.traj: not a trajectory file"):
        Trajectory.load(tmp_path / "junk.traj")
    with pytest.raises(ValueError, match=r"q: expected shape \(5, 22\), got \(4, 22\)"):
        Trajectory(name="t", robot="r", object="o", frame_rate=30.0, controls=np.zeros((5, 22)), q=np.zeros((4, 22)))


def test_shipped_trajectories_load():
    files = sorted(DATA_DIR.glob("*.traj"))
    assert files
    for f in files:
        t = Trajectory.load(f)
        assert t.truth is not None and t.frames > 100 and t.force.shape == (t.frames, 4, 3)


def test_groups_with_different_methods_update_by_their_own_rules():
    gen = torch.Generator().manual_seed(0)
    cost = torch.rand(3, 16, generator=gen) * 10
    upd = update(cost, OptimizerConfig(), gen, methods=("EYE", "PBO", "OLP"))
    identity = torch.arange(16)
    assert torch.equal(upd.index[0], identity) and torch.equal(upd.index[2], identity)
    assert not upd.explore[0].any() and not upd.explore[2].any()
    best_half = set(cost[1].argsort()[:8].tolist())
    assert set(upd.index[1].tolist()) <= best_half and upd.explore[1, 1:].all()


def test_charts_are_png_files(tmp_path):
    bar = bar_chart(tmp_path / "b.png", "ADD", ["LOW", "MED"], ["EYE", "PBO"], np.array([[3.0, 2.0], [5.0, np.nan]]))
    line = line_chart(tmp_path / "l.png", "ADD", {"EYE": np.linspace(0, 5, 90)}, x_step=1 / 30)
    points = {"med": [[10.1, 5.2], [15.5, 2.5]]}
    xy = xy_chart(tmp_path / "x.png", "ADD", points, "p99 [ms]", labels={"med": ["40", "1024"]})
    for path in (bar, line, xy):
        data = path.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
        width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        assert width >= 500 and height == 360


def test_the_benchmarks_page_is_generated_from_the_committed_results(tmp_path):
    from inhand_tracker.service.bench.publish import render

    root = Path(__file__).resolve().parents[1]
    results = tmp_path / "results"
    results.mkdir()
    for f in (root / "docs" / "results").glob("**/*.json"):
        copy = results / f.relative_to(root / "docs" / "results")
        copy.parent.mkdir(exist_ok=True)
        copy.write_text(f.read_text())
    page = render(results, tmp_path / "benchmarks.md")
    pages = sorted(p.name for p in tmp_path.glob("benchmarks*.md"))
    assert pages == sorted(p.name for p in (root / "docs").glob("benchmarks*.md"))
    for name in pages:
        ours = (tmp_path / name).read_text()
        assert ours == (root / "docs" / name).read_text(), f"{name}: run `inhand-tracker bench publish`"
    assert len(page.read_text().splitlines()) <= 250, "the benchmarks page: a short page per topic"
    assert (results / "01-accuracy-paper.png").stat().st_size > 1000
