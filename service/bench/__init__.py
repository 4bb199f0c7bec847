"""The benchmarks: accuracy suites (ground truth from scripted demos, ADD per track), the speed of
the whole tracker against its physics, the physics alone, and their reports.

Nothing outside this package imports it but the command line."""

from .accuracy import TrackResult, TrackSetting, run_suite, run_tracks
from .demos import DEMO_KINDS, Demo, Recording, make_demo, record, sensitivity
from .report import write_report
from .sim import SimBenchResult, bench_sim
from .speed import SpeedResult, bench_speed
from .suites import EXPLORATION, K_ABLATION, NOISE_LEVELS, SUITES, PhysicsGap, SensorNoise, Suite
from .truth import ground_truth

__all__ = [
    "DEMO_KINDS",
    "EXPLORATION",
    "K_ABLATION",
    "NOISE_LEVELS",
    "SUITES",
    "Demo",
    "PhysicsGap",
    "Recording",
    "SensorNoise",
    "SimBenchResult",
    "SpeedResult",
    "Suite",
    "TrackResult",
    "TrackSetting",
    "bench_sim",
    "bench_speed",
    "ground_truth",
    "make_demo",
    "record",
    "run_suite",
    "run_tracks",
    "sensitivity",
    "write_report",
]
