"""The benchmarks: accuracy suites (ground truth from scripted demos, ADD per track), the speed of
the whole tracker against its physics, the physics alone, and their reports; and the tracker
settings a robot's own recordings with truth call for (``check-settings``).

Nothing outside this package imports it but the command line."""

from .accuracy import parse_settings, run_suite
from .demos import DEMO_KINDS, Demo, make_demo
from .recorder import Recording, record, sensitivity
from .report import write_report
from .run import AccuracyRun
from .settings_check import CANDIDATES, OWN_SETTINGS, SettingsCheck, check_settings, settings_report, write_settings
from .sim import SimBenchResult, bench_sim
from .speed import SpeedResult, bench_speed
from .suites import EXPLORATION, K_ABLATION, NOISE_LEVELS, SUITES, PhysicsGap, SensorNoise, Suite
from .tracks import TrackResult, TrackSetting, run_tracks
from .truth import ground_truth

__all__ = [
    "CANDIDATES",
    "DEMO_KINDS",
    "EXPLORATION",
    "K_ABLATION",
    "NOISE_LEVELS",
    "OWN_SETTINGS",
    "SUITES",
    "AccuracyRun",
    "Demo",
    "PhysicsGap",
    "Recording",
    "SensorNoise",
    "SettingsCheck",
    "SimBenchResult",
    "SpeedResult",
    "Suite",
    "TrackResult",
    "TrackSetting",
    "bench_sim",
    "bench_speed",
    "check_settings",
    "ground_truth",
    "make_demo",
    "parse_settings",
    "record",
    "run_suite",
    "run_tracks",
    "sensitivity",
    "settings_report",
    "write_report",
    "write_settings",
]
