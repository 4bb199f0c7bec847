"""The `inhand-tracker` command line, run in-process through typer's runner (the service's own
process tests start it as a real process)."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from inhand_tracker.service.bench.suites import SUITES
from inhand_tracker.service.cli import app


def _run(*args: str):
    return CliRunner().invoke(app, list(args))


def test_bench_sim_prints_timings_and_memory_per_world():
    out = _run("bench", "sim", "--worlds", "2,4", "--frames", "3", "--device", "cpu", "--json")
    assert out.exit_code == 0, out.stderr[-2000:]
    rows = json.loads(out.stdout[out.stdout.index("[") :])
    assert [r["worlds"] for r in rows] == [2, 4]
    for r in rows:
        assert r["device"] == "cpu" and r["solver"] == "newton/sparse" and r["substeps"] == 8
        assert 0 < r["median_ms"] <= r["p95_ms"] and isinstance(r["bytes_per_world"], float)


def test_bench_rebuilds_reports_the_memory_before_and_after():
    out = _run("bench", "rebuilds", "--cycles", "10", "--worlds", "2", "--device", "cpu", "--json")
    assert out.exit_code == 0, out.stderr[-2000:]
    r = json.loads(out.stdout[out.stdout.index("{") :])
    assert r["cycles"] == 10 and r["worlds"] == 2 and r["build_s_mean"] > 0
    assert 0 < r["rss_mib_warm"] <= r["rss_mib_end"] * 1.5 and r["device_mib_end"] == 0.0
    assert r["command"] == "inhand-tracker bench rebuilds --cycles 10 --worlds 2 --device cpu"
    bad = _run("bench", "rebuilds", "--cycles", "3", "--device", "cpu")
    assert bad.exit_code == 2 and "expected cycles >= 10 and worlds >= 1, got 3, 8" in bad.stderr


def test_bad_arguments_are_refused_with_the_value():
    out = _run("bench", "sim", "--worlds", "40,abc")
    assert out.exit_code == 2 and "expected comma-separated integers, got '40,abc'" in out.stderr


def test_bad_tracker_settings_are_refused_with_the_name_and_value():
    for setting, message in [
        ("jitter_bandwith=0", "no setting 'jitter_bandwith'"),  # a typo: the names allowed follow
        ("update_every=x", "update_every: expected a value of type int, got 'x'"),
        ("jitter_t=-1", "'jitter_t': settings are named by their group, e.g. 'exploration.jitter_t'"),
        ("exploration.jitter_t=-1", "exploration.jitter_t: expected 0 to 0.1 m, got -1"),
        ("optimizer.pbo_keep=2", "optimizer.pbo_keep: expected 0 < fraction <= 1, got 2.0"),
        ("optimizer.keep_best=flase", "optimizer.keep_best: expected a value of type bool, got 'flase'"),
        ("population.tolerance=2", "population.tolerance: expected 0 < tolerance < 1, got 2.0"),
        ("population.substeps=4", "no setting 'population.substeps'"),  # --substeps sets it
        ("population.impratio=0", "population.impratio: expected > 0, got 0.0"),
        ("population.cone=round", "population.cone: expected 'pyramidal' or 'elliptic', got 'round'"),
        ("estimate.estimate_lambda=nan", "estimate.estimate_lambda: expected a finite number, got nan"),
    ]:
        out = _run("bench", "accuracy", "--suite", "smoke", "--set", setting)
        assert out.exit_code == 2 and message in out.stderr, (setting, out.stderr[-2000:])
    assert "exploration.jitter_bandwidth" in _run("bench", "accuracy", "--set", "jitter_bandwith=0").stderr


def test_bad_suite_options_are_refused_before_anything_runs():
    for args, message in [
        (("--suite", "huge"), f"--suite: expected one of {sorted(SUITES)}, got 'huge'"),
        (("--methods", "PBO,XYZ"), "methods: expected some of"),
        (("--ablations", "wrist"), "ablations: unknown ['wrist']"),
        (("--substeps", "3"), "substeps: expected a positive even number, got 3"),
        (("--repeats", "0"), "repeats: expected >= 1, got 0"),
    ]:
        out = _run("bench", "accuracy", "--device", "cpu", *args)
        assert out.exit_code == 2 and message in out.stderr, (args, out.stderr[-2000:])


def test_settings_split_into_the_tracker_and_its_physics():
    from inhand_tracker.service.bench import parse_settings
    from inhand_tracker.service.tracker import TERM_NAMES, WEIGHTS, changed

    config, physics = parse_settings(
        ["optimizer.pbo_keep=0.5", "population.impratio=30", "population.contact_gap=0.004"]
    )
    assert config.optimizer.pbo_keep == 0.5 and physics == {"impratio": 30.0, "contact_gap": 0.004}
    assert parse_settings(["optimizer.keep_best=no"])[0].optimizer.keep_best is False
    assert parse_settings([])[1] == {}
    # A cost term's weight by the term's name; the others keep theirs.
    weights = parse_settings(["cost.zone_force=0", "cost.joints=25"])[0].cost.weights
    differ = {name: (w, w0) for name, w, w0 in zip(TERM_NAMES, weights, WEIGHTS, strict=True) if w != w0}
    assert differ == {"joints": (25.0, 50.0), "zone_force": (0.0, 1.7)}
    with pytest.raises(ValueError, match=r"cost\.zone_force: expected a value of type float, got 'x'"):
        parse_settings(["cost.zone_force=x"])
    # A run's results name the changed weights as --set does.
    config = parse_settings(["cost.joints=25", "optimizer.min_separation=4"])[0]
    assert changed(config) == {"cost.joints": 25.0, "optimizer.min_separation": 4.0}
    # The robot's own settings (its config's [tracker] table) are where --set starts from.
    robot = {"optimizer.open_loop_ratio": 1.5, "update_every": 5}
    assert changed(parse_settings([], robot)[0]) == robot
    config = parse_settings(["optimizer.open_loop_ratio=0"], robot)[0]
    assert (config.optimizer.open_loop_ratio, config.update_every) == (0.0, 5)


def test_bench_speed_times_the_tracker_against_the_physics():
    out = _run("bench", "speed", "--worlds", "4", "--groups", "1,2", "--caps", "default,4x3", "--frames", "5",
               "--set", "population.tolerance=1e-5", "--set", "population.ls_tolerance=0.05", "--device", "cpu",
               "--json")  # fmt: skip
    assert out.exit_code == 0, out.stderr[-2000:]
    result = json.loads(out.stdout)
    command = (
        "inhand-tracker bench speed --worlds 4 --groups 1,2 --caps default,4x3 --frames 5"
        " --set population.tolerance=1e-5 --set population.ls_tolerance=0.05 --device cpu"
    )
    assert result["command"] == command  # each --set as typed, so the file's command runs again
    assert {(r["tolerance"], r["ls_tolerance"]) for r in result["results"]} == {(1e-5, 0.05)}
    assert re.search(r" x\d+$", result["device"])
    rows = result["results"]
    assert [(r["worlds"], r["groups"], r["iterations"], r["ls_iterations"]) for r in rows] == [
        (4, 1, 20, 10), (4, 2, 20, 10), (4, 1, 4, 3), (4, 2, 4, 3)
    ]  # fmt: skip
    for r in rows:
        assert r["device"] == "cpu" and r["frames"] == 5 and r["substeps"] == 8
        assert 0 < r["tracker_median_ms"] <= r["tracker_p99_ms"] and 0 < r["physics_median_ms"] <= r["physics_p99_ms"]
        assert r["ratio"] == r["tracker_median_ms"] / r["physics_median_ms"]
        assert r["world_substeps_per_s"] == pytest.approx(4 * 8 / (r["tracker_median_ms"] / 1e3))
        assert r["captured"] is False  # torch has no CPU graphs: plain calls around the physics graph
    bad = _run("bench", "speed", "--worlds", "5", "--groups", "2", "--device", "cpu")
    assert bad.exit_code == 2 and "worlds: 5 do not split into 2 groups" in bad.stderr
    bad = _run("bench", "speed", "--set", "exploration.jitter_bandwidth=0", "--device", "cpu")
    assert bad.exit_code == 2 and "--set: expected population.NAME=VALUE (the physics)" in bad.stderr
    bad = _run("bench", "speed", "--caps", "4x", "--device", "cpu")
    assert bad.exit_code == 2 and "caps: expected ITERATIONSxLINE_SEARCH" in bad.stderr


def test_version_names_the_package_and_the_protocol():
    from inhand_tracker.protocol import PROTOCOL_VERSION

    out = _run("--version")
    assert out.exit_code == 0 and out.stdout.startswith("inhand-tracker ")
    assert f"protocol v{PROTOCOL_VERSION}" in out.stdout


def test_a_simulating_command_without_the_gpu_stack_says_what_to_install(monkeypatch):
    import importlib.util

    found = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "newton" else found(name, *a))
    out = _run("bench", "sim", "--worlds", "2", "--device", "cpu")  # as on the robot side's light install
    assert out.exit_code == 2 and "(missing: newton)" in out.stderr, out.stderr
    assert "pip install '.[service]' in the repository" in out.stderr


def test_a_simulating_command_loads_the_stack_out_of_the_collector_s_view():
    # In a process of its own: the stack is loaded once per process, and here it already is.
    code = (
        "import gc; from inhand_tracker.service.cli.common import gpu_stack; gpu_stack();"
        " print(gc.isenabled(), gc.get_freeze_count())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    enabled, frozen = out.stdout.split()
    # The collector runs again for what the command makes, and walks none of the stack's objects.
    assert enabled == "True" and int(frozen) > 500_000, out.stdout


def test_an_endpoint_without_its_transport_is_answered_in_one_line_within_a_second(tmp_path):
    """The likeliest typo of all, `127.0.0.1:7447` for `tcp/127.0.0.1:7447`: one line, the spelling
    to use, exit 2, before torch or warp load (a real process, timed)."""
    import subprocess
    import sys
    import time

    from inhand_tracker.service.paths import DATA_DIR

    traj = str(DATA_DIR / "smoke-foam_brick_pick_place_0.traj")
    for args, said in [
        (
            ["serve", "--listen", "127.0.0.1:7447"],
            "serve --listen: '127.0.0.1:7447' is not a Zenoh endpoint; write it as tcp/127.0.0.1:7447",
        ),
        (["replay", traj, "--connect", "127.0.0.1:7447"], "replay --connect: '127.0.0.1:7447' is not a Zenoh endpoint"),
        (
            ["watch", "--connect", "localhost"],
            "watch --connect: 'localhost' is not a Zenoh endpoint; write it as tcp/HOST:PORT",
        ),
    ]:
        began = time.monotonic()
        out = subprocess.run(
            [sys.executable, "-m", "inhand_tracker.service.cli", *args], capture_output=True, text=True, cwd=tmp_path
        )
        seconds = time.monotonic() - began
        lines = [line for line in out.stderr.splitlines() if line.strip()]
        assert out.returncode == 2 and lines == [lines[0]] and said in lines[0], (args, out.stderr)
        assert seconds < 3.0, (args, seconds)  # under a second here; a loaded CI core gets room
    from inhand_tracker.service.server.config import load_config

    with pytest.raises(ValueError, match=r"service config connect: .*'router:7447' is not a Zenoh endpoint"):
        load_config(connect=("router:7447",))
