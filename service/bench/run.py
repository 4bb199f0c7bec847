"""One accuracy run's settings: a suite, what tracks it, and how (:func:`.accuracy.run_suite` runs it)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from inhand_tracker.protocol import DEFAULT_WORLDS, Trajectory
from inhand_tracker.service.paths import CACHE_DIR
from inhand_tracker.service.tracker import METHODS, TrackerConfig
from inhand_tracker.sim_backend import PopulationConfig, RobotSpec

from .suites import K_ABLATION, NOISE_LEVELS, Suite

__all__ = ["ABLATIONS", "OBSERVATIONS", "AccuracyRun"]

OBSERVATIONS = ("none", "ends", "1hz", "visible")
"""When a camera's pose estimate reaches the tracker: never (the paper), on the first and last
frame (the paper's real-world protocol), once a second, or once a second while the fingers touch
nothing (a closed hand hides the object)."""

ABLATIONS = ("exploration", "worlds", "contact", "slip")
"""The paper's Fig. 3 studies, each PBO at medium noise with one thing changed."""


@dataclass(frozen=True)
class AccuracyRun:
    """One accuracy run: a suite, what tracks it, and how. Checked when made, each refusal naming
    the field and the value."""

    suite: Suite
    methods: tuple[str, ...] = METHODS
    noises: tuple[str, ...] = ("low", "med", "high")
    """Initial pose noise levels (:data:`.suites.NOISE_LEVELS`)."""
    worlds: int = DEFAULT_WORLDS
    """K, worlds per track (OLP always simulates one)."""
    ablations: tuple[str, ...] = ()
    """Which of :data:`ABLATIONS` to run as well."""
    k_ablation: tuple[int, ...] = K_ABLATION
    """The worlds ablation's K."""
    repeats: int = 1
    """Independent runs of every track, batched as more groups: each draws its own starts."""
    config: TrackerConfig = field(default_factory=TrackerConfig)
    """The tracker's settings; its seed is the suite's."""
    substeps: int = PopulationConfig.substeps
    """The tracker's physics substeps per frame (the ground truth keeps its suite's own)."""
    population: dict[str, int | float | bool] = field(default_factory=dict)
    """The tracker's other physics settings where they differ from PopulationConfig's defaults,
    e.g. ``{"impratio": 30.0}`` (the ground truth keeps the defaults and its suite's gap)."""
    observations: str = "none"
    """When a camera's pose reaches the tracker (:data:`.tracks.OBSERVATIONS`): the true pose with
    ``vision_sigma`` of noise, reported as its covariance."""
    vision_sigma: tuple[float, float] = (0.005, 0.05)
    """The camera's noise, position [m] and rotation [rad]."""
    device: str = "auto"
    cache: Path | None = CACHE_DIR
    """Where generated ground truth is kept (None: nowhere)."""
    quiet: bool = False
    """No progress bar."""
    files: tuple[Trajectory, ...] = ()
    """The user's own trajectories to score instead of the suite's truth, each with its ground
    truth, e.g. from motion capture (:func:`load_files`; :func:`files_suite` describes them)."""
    servos: tuple[tuple[str, tuple[float, ...]], ...] = ()
    """The tracker's robot servos in place of its config's, as a calibration's overlay sets them
    (:attr:`sim_backend.FileRobotSpec.servos`); the truth keeps its own."""
    robot: RobotSpec | None = None
    """The tracker's robot in place of the config its trajectories name: a config of the user's own
    (``check-settings``); None: ``configs/robots``' config of that name."""
    frames_to: Path | None = None
    """Where :func:`.tracks.save_frames` writes every track's per-frame estimate against the truth."""

    def __post_init__(self) -> None:
        if self.observations not in OBSERVATIONS:
            raise ValueError(f"observations: expected one of {OBSERVATIONS}, got {self.observations!r}")
        for m in self.methods:
            if m not in METHODS:
                raise ValueError(f"methods: expected some of {METHODS}, got {m!r}")
        for n in self.noises:
            if n not in NOISE_LEVELS:
                raise ValueError(f"noise: expected some of {tuple(NOISE_LEVELS)}, got {n!r}")
        if self.repeats < 1:
            raise ValueError(f"repeats: expected >= 1, got {self.repeats}")
        unknown = sorted(set(self.ablations) - set(ABLATIONS))
        if unknown:
            raise ValueError(f"ablations: unknown {unknown}; expected exploration, worlds, contact, slip or all")
        if self.substeps < 2 or self.substeps % 2:
            raise ValueError(f"substeps: expected a positive even number, got {self.substeps}")

    @property
    def physics(self) -> dict[str, int | float | bool]:
        """The tracker's PopulationConfig settings other than its layout."""
        return {"substeps": self.substeps, **self.population}
