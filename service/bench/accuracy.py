"""The accuracy benchmark: section IV-A of the paper on synthetic ground truth, and beyond it.

A suite is a set of scripted demos (objects x kinds x variants) recorded with hidden mass and
friction drawn from the prior, optionally with the truth's physics off from the tracker's and
with sensor noise (the reality gap). Every track (trajectory x initial-noise level x method, or
an ablation setting) is one group of one population per object, so a suite is one batched run
(:mod:`.tracks`). The tracker sees only what the robot sends plus a noisy initial pose; ADD scores
every frame.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.tracker import (
    TrackerConfig,
    settings,
)

from .progress import progress_bar
from .run import AccuracyRun
from .suites import Suite
from .tracks import TrackResult, TrackSetting, per_frame, plan_tracks, run_tracks, save_frames
from .truth import ground_truth, open_loop_disagreement

__all__ = ["files_suite", "load_files", "parse_settings", "run_suite"]

log = logging.getLogger(__name__)


def load_files(paths: Sequence[Path]) -> tuple[Trajectory, ...]:
    """The trajectories of a user's ``.traj`` files; a ValueError names a file that cannot be read,
    carries no ground truth (a session recording never does), or is of another robot."""
    from inhand_tracker.protocol.recording import load_trajectory

    out: list[Trajectory] = []
    for path in paths:
        try:
            t = load_trajectory(path)
        except (OSError, ValueError) as exc:
            raise ValueError(f"files: {exc}") from None
        if t.truth is None:
            raise ValueError(f"files: '{path}' carries no ground truth (the object's true pose per frame)")
        if out and t.robot != out[0].robot:
            raise ValueError(f"files: '{path}' is of robot '{t.robot}', the first file's is '{out[0].robot}'")
        out.append(t)
    return tuple(out)


def files_suite(trajectories: Sequence[Trajectory]) -> Suite:
    """The suite a user's trajectories make: their objects and robot, as they were recorded."""
    objects = tuple(dict.fromkeys(t.object for t in trajectories))
    seconds = max(t.frames / t.frame_rate for t in trajectories)
    return Suite("files", objects, (), 1, seconds=round(seconds, 1), robot=trajectories[0].robot)


def parse_settings(items: Sequence[str], defaults: Mapping[str, object] | None = None) -> tuple[TrackerConfig, dict]:
    """A TrackerConfig and the population's physics overrides (by PopulationConfig's field names)
    from ``--set`` NAME=VALUE strings, by the settings' dotted names (:mod:`..tracker.settings`):
    ``exploration.jitter_bandwidth=0.5``, ``optimizer.min_separation=4``, ``cost.zone_force=0``,
    ``population.impratio=30``; they change the robot's own ``defaults`` (its config's ``[tracker]``
    table, :func:`..tracker.settings.robot_defaults`), as a session's overrides do. The layout's and the
    suite's own (seed, substeps) have their flags. A bad name or value is a ValueError naming it."""
    allowed = [n for n in settings.registry() if n not in ("seed", "population.substeps")]
    tracker, physics = settings.split(settings.parse(items, allowed))
    return settings.tracker_config(dict(defaults or {}) | tracker), physics


def run_suite(run: AccuracyRun, checkpoint: Callable[[dict], None] | None = None) -> dict:
    """Ground truth, then every object's tracks as one batched run; returns the results as a dict
    (``summary`` per method and noise, ``ablations``, ``tracks`` with per-frame ADD). ``checkpoint``
    gets the partial results after each population."""
    t0 = time.perf_counter()
    trajectories = list(run.files) if run.files else ground_truth(run.suite, run.device, run.cache)
    t_truth = time.perf_counter() - t0
    by_object: dict[str, list[Trajectory]] = {}
    for t in trajectories:
        by_object.setdefault(t.object, []).append(t)
    plan = {
        o: plan_tracks(len(ts), run.methods, run.noises, run.ablations, run.worlds, run.k_ablation, run.repeats)
        for o, ts in by_object.items()
    }
    total = sum(max(t.frames for t in by_object[o]) * sum(s.worlds for s in p) for o, p in plan.items())
    bar = progress_bar(total, "tracking", unit="world-frames", disable=run.quiet)
    results: list[TrackResult] = []
    for o, ts in by_object.items():
        drift, pressing = open_loop_disagreement(ts, run.device, run.physics, run.servos)
        first = len(results)
        by_k: dict[int, list[TrackSetting]] = {}
        for s in plan[o]:
            by_k.setdefault(s.worlds, []).append(s)
        for k, k_tracks in by_k.items():  # the frames of one population advance all its groups at once
            t1 = time.perf_counter()
            results += run_tracks(ts, k_tracks, run, bar.update)
            for r in results[first:]:
                r.open_loop = drift[: r.add.shape[0], r.setting.trajectory]
                r.open_loop_force_ratio = float(pressing[r.setting.trajectory])
            frames, seconds = max(t.frames for t in ts), time.perf_counter() - t1
            log.info(
                f"tracked {o}: {len(k_tracks)} tracks x {k} worlds, {frames} frames in {seconds:.0f} s"
                f" ({1e3 * seconds / frames:.1f} ms per frame)"
            )
            if checkpoint:  # what is done so far survives a run cut short (a time limit)
                checkpoint(_collect(run, results, t_truth, time.perf_counter() - t0))
    bar.close()
    t_track = time.perf_counter() - t0 - t_truth
    if run.frames_to is not None:
        save_frames(results, run.frames_to)
    return _collect(run, results, t_truth, t_track)


def _stats(results: Sequence[TrackResult], of: str = "add") -> dict:
    """Mean, std and max over tracks of each track's mean ADD [mm] (``of`` the estimate, or of the
    lowest-cost world: "add_best"); with several repeats also the mean of each run, whose spread says
    how far one run's mean is to be trusted."""
    a = np.array([getattr(r, of).mean() for r in results]) * 1e3
    out = {"mean_mm": float(a.mean()), "std_mm": float(a.std()), "max_mm": float(a.max()), "tracks": int(a.size)}
    runs = np.array([r.setting.repeat for r in results])
    if runs.max() > 0:
        out["run_means_mm"] = [float(a[runs == r].mean()) for r in np.unique(runs)]
    return out


def _collect(run: AccuracyRun, results: list[TrackResult], t_truth: float, t_track: float) -> dict:
    """ADD statistics over tracks: mean of per-track mean ADD, its std over tracks, and the max
    over all frames, per method and noise level (Fig. 2) and per ablation setting (Fig. 3)."""
    worlds, k_ablation = run.worlds, run.k_ablation
    summary: dict[str, dict[str, dict]] = {}
    for r in results:
        s = r.setting
        if s.study == "main":
            summary.setdefault(s.method, {}).setdefault(s.noise, []).append(r)
    fig2, best_world = (
        {
            m: {
                n: {**_stats(rs, of), "max_mm": float(max(getattr(r, of).max() for r in rs) * 1e3)}
                for n, rs in by_noise.items()
            }
            for m, by_noise in summary.items()
        }
        for of in ("add", "add_best")
    )
    for m, by_noise in summary.items():  # what contact cannot see, and how honest the uncertainty is
        for n, rs in by_noise.items():
            fig2[m][n]["add_s_mean_mm"] = float(np.mean([r.add_s.mean() for r in rs]) * 1e3)
            fig2[m][n]["coverage_95"] = float(np.mean([r.covered.mean() for r in rs]))
            if medians := [r.evidence() for r in rs if r.evidence()]:  # how far the sensing told the worlds apart
                for key in medians[0]:
                    fig2[m][n][key] = float(np.median([e[key] for e in medians]))
            onsets, said = np.sum([r.flagged() for r in rs], axis=0)
            fig2[m][n]["error_onsets"], fig2[m][n]["flagged_within_1s"] = int(onsets), int(said)
            if events := [r.after_event() for r in rs if r.event is not None]:  # a loss suite
                for key, i in (("flag_after_s", 0), ("back_within_10mm_after_s", 1)):
                    times = [e[i] for e in events if e[i] is not None]
                    fig2[m][n][key] = float(np.mean(times)) if times else None
                    fig2[m][n][key.replace("_after_s", "_never")] = len(events) - len(times)
    ablation: dict[str, dict[str, dict]] = {}

    def add_row(study: str, label: str, rs: list[TrackResult]) -> None:
        if rs:
            ablation.setdefault(study, {})[label] = _stats(rs)

    base = [r for r in results if r.setting.study == "main" and r.setting.method == "PBO" and r.setting.noise == "med"]
    studies = {r.setting.study for r in results} - {"main"}
    if "exploration" in studies:
        for e in ("low", "med", "high"):
            rs = (
                base
                if e == "med"
                else [r for r in results if r.setting.study == "exploration" and r.setting.exploration == e]
            )
            add_row("exploration", e, rs)
    if "worlds" in studies:
        for k in sorted({*k_ablation, worlds}):
            rs = base if k == worlds else [r for r in results if r.setting.study == "worlds" and r.setting.worlds == k]
            add_row("worlds", str(k), rs)
    for study in ("contact", "slip"):
        if study in studies:
            add_row(study, "on", base)
            add_row(study, "off", [r for r in results if r.setting.study == study])
    vision = {"schedule": run.observations}
    if run.observations != "none":
        vision["vision_sigma"] = list(run.vision_sigma)
    return {
        "suite": asdict(run.suite),
        "device": run.device,
        "worlds": worlds,
        "repeats": 1 + max((r.setting.repeat for r in results), default=0),
        "tracker": settings.changed(run.config),
        "substeps": run.substeps,
        "population": dict(run.population),
        **({"servos": {k: list(v) for k, v in run.servos}} if run.servos else {}),
        "observations": vision,
        "seconds": {"ground_truth": t_truth, "tracking": t_track},
        "summary": fig2,
        "summary_best_world": best_world,
        "ablations": ablation,
        "tracks": [r.summary() | per_frame(r) for r in results],
    }
