"""The `inhand-tracker` command as a user runs it: a real process."""

from __future__ import annotations

import json
import subprocess
import sys


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True, timeout=600)


def test_bench_sim_prints_timings_and_memory_per_world():
    out = _run("bench", "sim", "--worlds", "2,4", "--frames", "3", "--device", "cpu", "--json")
    assert out.returncode == 0, out.stderr[-2000:]
    rows = json.loads(out.stdout[out.stdout.index("[") :])
    assert [r["worlds"] for r in rows] == [2, 4]
    for r in rows:
        assert r["device"] == "cpu" and r["solver"] == "cg" and r["substeps"] == 8
        assert 0 < r["median_ms"] <= r["p95_ms"] and isinstance(r["bytes_per_world"], float)


def test_bad_arguments_are_refused_with_the_value():
    out = _run("bench", "sim", "--worlds", "40,abc")
    assert out.returncode == 2 and "expected comma-separated integers, got '40,abc'" in out.stderr
