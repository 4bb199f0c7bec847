"""The accuracy benchmark: section IV-A of the paper on synthetic ground truth, and beyond it.

A suite is a set of scripted demos (objects x kinds x variants) recorded with hidden mass and
friction drawn from the prior, optionally with the truth's physics off from the tracker's and
with sensor noise (the reality gap). Every track (trajectory x initial-noise level x method, or
an ablation setting) is one group of one population per object, so a suite is one batched run.
The tracker sees only what the robot sends plus a noisy initial pose; ADD scores every frame.
"""

from __future__ import annotations

import functools
import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from protocol import DEFAULT_WORLDS, TrackState, Trajectory
from service.evaluation import add_error, adds_error, pose_error, within_region
from service.paths import CACHE_DIR
from service.tracker import METHODS, Frame, Tracker, TrackerConfig
from service.tracker.sampling import sample_poses
from sim_backend import Population, PopulationConfig, catalog_object

from .demos import Recording
from .progress import progress_bar
from .suites import EXPLORATION, K_ABLATION, NOISE_LEVELS, Suite, robot_spec
from .truth import ground_truth, open_loop_disagreement

__all__ = ["OBSERVATIONS", "TrackResult", "TrackSetting", "run_suite", "run_tracks", "save_frames", "settings"]

log = logging.getLogger(__name__)

OBSERVATIONS = ("none", "ends", "1hz", "visible")
"""When a camera's pose estimate reaches the tracker: never (the paper), on the first and last
frame (the paper's real-world protocol), once a second, or once a second while the fingers touch
nothing (a closed hand hides the object)."""
_ADDS_EVERY = 10
"""ADD-S is scored on every tenth frame (a nearest-point search per surface point)."""

_CONTACT_TERMS = (3, 4, 5)  # contact disagreement, force magnitude, force direction
_SLIP_TERMS = (6, 7, 8, 9)


# ---------------------------------------------------------------------- tracks
@dataclass(frozen=True)
class TrackSetting:
    """What one group of the batched run does."""

    trajectory: int
    noise: str
    method: str
    worlds: int = DEFAULT_WORLDS
    exploration: str = "med"
    contact_terms: bool = True
    slip_terms: bool = True
    study: str = "main"
    """main (Fig. 2) or the ablation it belongs to (exploration, worlds, contact, slip)."""
    repeat: int = 0
    """Which run of the suite the track belongs to: each run draws its own noisy initial poses
    and its own tracker noise, so several runs put an interval on a suite's mean."""


@dataclass
class TrackResult:
    setting: TrackSetting
    trajectory: str
    object: str
    add: np.ndarray = field(repr=False)
    """ADD of the estimate per frame, (F,) [m]."""
    add_best: np.ndarray = field(repr=False)
    """ADD of the lowest-cost world's pose (the paper's estimate) per frame, (F,) [m]."""
    diverged: int = 0
    """Frames on which the tracker re-seeded the group."""
    add_s: np.ndarray | None = field(default=None, repr=False)
    """ADD-S of the estimate on every tenth frame, [m]."""
    covered: np.ndarray | None = field(default=None, repr=False)
    """Whether the truth lay in the estimate's reported 95 % region, per frame, (F,) bool."""
    status: np.ndarray | None = field(default=None, repr=False)
    """The estimate's track state per frame, (F,) int (:class:`protocol.TrackState`)."""
    event: int | None = None
    """The frame the object was lost (slipped out of the hand) in the truth, on a loss suite."""
    frames: dict[str, np.ndarray] | None = field(default=None, repr=False)
    """What the estimate said each frame against the truth (:func:`save_frames`): ``error`` (F, 6)
    the true pose seen from the estimate [m, rad], ``covariance`` (F, 6, 6) as reported, ``cost``
    (F,) the lowest window cost and ``lost`` (F,) the share of worlds that lost the object."""

    def after_event(self, within: float = 0.01, hold: int = 15) -> tuple[float | None, float | None]:
        """Seconds from the loss to the status first saying anything but tracking, and to the
        estimate coming back within ``within`` [m] for ``hold`` frames; None: never."""
        if self.event is None or self.status is None:
            return None, None
        rate = 30.0
        said = np.flatnonzero(self.status[self.event :] != TrackState.TRACKING)
        near = self.add[self.event :] <= within
        stays = np.convolve(near, np.ones(hold), "valid") == hold
        back = np.flatnonzero(stays)
        return (
            float(said[0] / rate) if said.size else None,
            float(back[0] / rate) if back.size else None,
        )

    def flagged(self, error: float = 0.02, within: int = 30) -> tuple[int, int]:
        """How often the estimate's error rose past ``error`` [m], and how many of those times its
        status said it was not to be trusted (anything but tracking) within ``within`` frames."""
        over = self.add > error
        onsets = np.flatnonzero(over & ~np.r_[False, over[:-1]])
        if self.status is None:
            return len(onsets), 0
        said = [(self.status[f : f + within + 1] != TrackState.TRACKING).any() for f in onsets]
        return len(onsets), int(np.sum(said))

    contacts_explored: bool | None = None
    """Whether the tracker's worlds explored their contacts by the track's end: its lowest cost
    said the model's contacts were wrong (:attr:`TrackerConfig.contact_gate_cost`)."""
    open_loop: np.ndarray | None = field(default=None, repr=False)
    """ADD of the tracker's physics run open loop from the true start with the true mass and
    friction, per frame, (F,) [m]: how far the engines disagree about this track's motion."""

    def summary(self) -> dict:
        return {
            **asdict(self.setting),
            "trajectory": self.trajectory,
            "object": self.object,
            "add_mean_mm": float(self.add.mean() * 1e3),
            "add_max_mm": float(self.add.max() * 1e3),
            "best_world_add_mean_mm": float(self.add_best.mean() * 1e3),
            "diverged_frames": self.diverged,
            **({} if self.contacts_explored is None else {"contacts_explored": self.contacts_explored}),
            **({} if self.add_s is None else {"add_s_mean_mm": float(self.add_s.mean() * 1e3)}),
            **({} if self.covered is None else {"coverage_95": float(self.covered.mean())}),
            **(
                {}
                if self.status is None
                else {
                    "error_onsets": self.flagged()[0],
                    "flagged_within_1s": self.flagged()[1],
                    "ambiguous_frames": int((self.status == TrackState.AMBIGUOUS).sum()),
                }
            ),
            **(
                {}
                if self.event is None
                else {
                    "event_frame": self.event,
                    "flag_after_s": self.after_event()[0],
                    "back_within_10mm_after_s": self.after_event()[1],
                }
            ),
            **(
                {}
                if self.open_loop is None
                else {
                    "open_loop_mean_mm": float(self.open_loop.mean() * 1e3),
                    "open_loop_max_mm": float(self.open_loop.max() * 1e3),
                }
            ),
        }


def settings(
    trajectories: int,
    methods: Sequence[str],
    noises: Sequence[str],
    ablations: Sequence[str],
    worlds: int,
    k_ablation: Sequence[int] = K_ABLATION,
    repeats: int = 1,
) -> list[TrackSetting]:
    """The tracks of a run: every trajectory x noise x method, then the ablations (PBO at medium
    noise, as the paper's Fig. 3); all of it ``repeats`` times."""
    out: list[TrackSetting] = []
    for r in range(repeats):
        # OLP simulates the initial estimate alone: one world, in a population of its own.
        out += [
            TrackSetting(t, n, m, 1 if m == "OLP" else worlds, repeat=r)
            for t in range(trajectories)
            for n in noises
            for m in methods
        ]
        ablation = functools.partial(TrackSetting, noise="med", method="PBO", repeat=r)
        for t in range(trajectories):
            if "exploration" in ablations:
                out += [ablation(t, worlds=worlds, exploration=e, study="exploration") for e in ("low", "high")]
            if "contact" in ablations:
                out.append(ablation(t, worlds=worlds, contact_terms=False, study="contact"))
            if "slip" in ablations:
                out.append(ablation(t, worlds=worlds, slip_terms=False, study="slip"))
            if "worlds" in ablations:
                out += [ablation(t, worlds=k, study="worlds") for k in k_ablation if k != worlds]
    return out


def run_tracks(
    trajectories: Sequence[Trajectory],
    tracks: Sequence[TrackSetting],
    device: str = "auto",
    seed: int = 0,
    progress: Callable[[int], None] | None = None,
    substeps: int = PopulationConfig.substeps,
    config: TrackerConfig | None = None,
    population: dict[str, int | float | bool] | None = None,
    observations: str = "none",
    vision_sigma: tuple[float, float] = (0.005, 0.05),
) -> list[TrackResult]:
    """Run ``tracks`` on ``trajectories`` of one object: one population per world count, every
    track a group of it. The noisy initial pose of a (trajectory, noise) pair is the same for
    every method, so methods are compared on equal footing; each repeat draws its own.
    ``population``: the tracker's physics settings other than PopulationConfig's defaults.
    ``observations``: when a camera's pose reaches the tracker (:data:`OBSERVATIONS`), the true
    pose with ``vision_sigma`` (position [m], rotation [rad]) of noise, reported as its covariance."""
    if observations not in OBSERVATIONS:
        raise ValueError(f"observations: expected one of {OBSERVATIONS}, got {observations!r}")
    obj = catalog_object(trajectories[0].object)
    spec = robot_spec(trajectories[0].robot)
    rec = Recording.stack(trajectories)
    gen = torch.Generator().manual_seed(seed)
    start = torch.tensor(rec.initial_pose, dtype=torch.float32)
    # The "vision" estimates, per noise level and repeat; repeat 0 draws what a single run always drew.
    repeats = max(t.repeat for t in tracks) + 1
    p0 = {(n, r): _noisy(start, *NOISE_LEVELS[n], gen) for r in range(repeats) for n in NOISE_LEVELS}
    points = obj.surface_points(1000)
    results: list[TrackResult] = []
    for k in sorted({t.worlds for t in tracks}):
        group = [t for t in tracks if t.worlds == k]
        physics = PopulationConfig(groups=len(group), worlds=k, device=device, substeps=substeps, **(population or {}))
        pop = Population(spec, obj, physics)
        terms = np.ones((len(group), 10), bool)
        for g, t in enumerate(group):
            terms[g, list(_CONTACT_TERMS)] = t.contact_terms
            terms[g, list(_SLIP_TERMS)] = t.slip_terms
        tracker = Tracker(
            pop,
            replace(config or TrackerConfig(), seed=seed),
            methods=[t.method for t in group],
            exploration=[EXPLORATION[t.exploration] for t in group],
            terms=terms,
        )
        rows = np.array([t.trajectory for t in group])
        tracker.start(
            np.stack([p0[t.noise, t.repeat][t.trajectory] for t in group]),
            rec.initial_q[rows],
            sigma_t=np.array([NOISE_LEVELS[t.noise][0] for t in group]),
            sigma_r=np.array([NOISE_LEVELS[t.noise][1] for t in group]),
        )
        poses = np.empty((rec.frames, len(group), 7), np.float32)
        bests = np.empty_like(poses)
        covariances = np.empty((rec.frames, len(group), 6, 6), np.float32)
        statuses = np.empty((rec.frames, len(group)), np.int64)
        costs = np.empty((rec.frames, len(group)), np.float32)
        lost = np.empty_like(costs)
        diverged = np.zeros(len(group), np.int64)
        seen = _observed(rec, observations)[:, rows]  # (F, G)
        events = [int(x) if (x := t.meta.get("drop_frame")) is not None else None for t in trajectories]
        vision_torch = torch.Generator().manual_seed(seed + 1)
        cov = np.diag([vision_sigma[0] ** 2] * 3 + [vision_sigma[1] ** 2] * 3)
        for f in range(rec.frames):
            est = tracker.step(Frame(**{name: v[f, rows] for name, v in rec.sensing.items()}))
            poses[f] = est.pose
            bests[f] = est.best_pose
            covariances[f] = est.covariance
            statuses[f] = est.status
            costs[f] = est.cost
            lost[f] = est.lost
            diverged += est.status == TrackState.DIVERGED
            for g in np.flatnonzero(seen[f]):
                noisy = _noisy(torch.tensor(rec.object_pose[f, rows[g]][None]), *vision_sigma, vision_torch)[0]
                tracker.observe(int(g), noisy, cov)
            if progress:
                progress(len(group) * k)
        explored = est.contacts_explored
        truth = rec.object_pose[:, rows]
        add = add_error(points, truth, poses)  # (F, G)
        add_best = add_error(points, truth, bests)
        add_s = adds_error(points[:200], truth[::_ADDS_EVERY], poses[::_ADDS_EVERY])
        error = pose_error(truth, poses)
        inside = within_region(error, covariances)
        error = error.astype(np.float32)
        for g, t in enumerate(group):
            n = int(rec.lengths[t.trajectory])
            name = rec.names[t.trajectory]
            frames = {"error": error, "covariance": covariances, "cost": costs, "lost": lost}
            frames = {k: v[:n, g] for k, v in frames.items()}
            results.append(
                TrackResult(t, name, obj.name, add[:n, g], add_best[:n, g], int(diverged[g]),
                            add_s[: -(-n // _ADDS_EVERY), g], inside[:n, g], statuses[:n, g],
                            events[t.trajectory], frames, bool(explored[g]))
            )  # fmt: skip
    return results


def _per_frame(r: TrackResult) -> dict:
    """A track's per-frame series for results.json: ADD [mm] and, where kept, the track state
    (:class:`protocol.TrackState` values), so that a miss can be found frame by frame."""
    out = {"add_mm": np.round(r.add * 1e3, 3).tolist()}
    if r.status is not None:
        out["status"] = r.status.astype(int).tolist()
    return out


def save_frames(results: Sequence[TrackResult], path: Path) -> None:
    """Every track's per-frame estimate against the truth (:attr:`TrackResult.frames`) as one
    ``.npz``: arrays ``{i}/{name}`` for track i of ``tracks``, a JSON list of the tracks' settings,
    so that a reported uncertainty can be checked, or recalibrated, without running the suite again."""
    arrays = {f"{i}/{k}": v for i, r in enumerate(results) for k, v in (r.frames or {}).items()}
    index = [{**asdict(r.setting), "trajectory": r.trajectory, "object": r.object} for r in results]
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, tracks=np.array(json.dumps(index)), **arrays)


def _observed(rec: Recording, schedule: str, rate: int = 30) -> np.ndarray:
    """Which frames a camera's pose reaches the tracker on, per trajectory, (F, T) bool."""
    frames, tracks = rec.frames, len(rec.names)
    out = np.zeros((frames, tracks), bool)
    if schedule == "ends":
        out[0] = True
        out[np.minimum(rec.lengths, frames) - 1, np.arange(tracks)] = True
    elif schedule in ("1hz", "visible"):
        out[::rate] = True
        if schedule == "visible" and rec.sensing.get("force") is not None:
            out &= ~(np.linalg.norm(rec.sensing["force"], axis=-1) > 0.05).any(-1)  # the fingers hide it
    return out & (np.arange(frames)[:, None] < rec.lengths[None])


def _noisy(mean: torch.Tensor, sigma_t: float, sigma_r: float, gen: torch.Generator) -> np.ndarray:
    pose = sample_poses(mean, sigma_t, sigma_r, 1, gen)[:, 0]
    return torch.cat([pose[:, :3], torch.nn.functional.normalize(pose[:, 3:], dim=-1)], dim=-1).numpy()


# ---------------------------------------------------------------------- a whole suite
def run_suite(
    suite: Suite,
    methods: Sequence[str] = METHODS,
    noises: Sequence[str] = ("low", "med", "high"),
    worlds: int = DEFAULT_WORLDS,
    ablations: Sequence[str] = (),
    device: str = "auto",
    cache: Path | None = CACHE_DIR,
    quiet: bool = False,
    k_ablation: Sequence[int] | None = None,
    checkpoint: Callable[[dict], None] | None = None,
    substeps: int = PopulationConfig.substeps,
    repeats: int = 1,
    config: TrackerConfig | None = None,
    population: dict[str, int | float | bool] | None = None,
    observations: str = "none",
    vision_sigma: tuple[float, float] = (0.005, 0.05),
    frames_to: Path | None = None,
) -> dict:
    """Ground truth, then every object's tracks as one batched run; returns the results as a dict
    (``summary`` per method and noise, ``ablations``, ``tracks`` with per-frame ADD). ``checkpoint``
    gets the partial results after each population. ``substeps``: the tracker's physics substeps per
    frame (the ground truth keeps its suite's own). ``repeats``: independent runs of every track,
    batched as more groups; the summary then also gives each run's mean. ``config``: the tracker's
    settings (default ``TrackerConfig()``; its seed is the suite's). ``population``: the tracker's
    physics settings other than PopulationConfig's defaults, e.g. ``{"impratio": 30.0}`` (the
    ground truth keeps the defaults and its suite's gap). ``observations``, ``vision_sigma``: a
    camera's pose estimates reaching the tracker (:func:`run_tracks`). ``frames_to``: where
    :func:`save_frames` writes every track's per-frame estimate against the truth."""
    if observations not in OBSERVATIONS:
        raise ValueError(f"observations: expected one of {OBSERVATIONS}, got {observations!r}")
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"methods: expected some of {METHODS}, got {m!r}")
    for n in noises:
        if n not in NOISE_LEVELS:
            raise ValueError(f"noise: expected some of {tuple(NOISE_LEVELS)}, got {n!r}")
    if repeats < 1:
        raise ValueError(f"repeats: expected >= 1, got {repeats}")
    unknown = sorted(set(ablations) - {"exploration", "worlds", "contact", "slip"})
    if unknown:
        raise ValueError(f"ablations: unknown {unknown}; expected exploration, worlds, contact, slip or all")
    if substeps < 2 or substeps % 2:
        raise ValueError(f"substeps: expected a positive even number, got {substeps}")
    vision = {"schedule": observations, "vision_sigma": list(vision_sigma)} if observations != "none" else None
    t0 = time.perf_counter()
    trajectories = ground_truth(suite, device, cache)
    t_truth = time.perf_counter() - t0
    by_object: dict[str, list[Trajectory]] = {}
    for t in trajectories:
        by_object.setdefault(t.object, []).append(t)
    k_ablation = tuple(k_ablation or K_ABLATION)
    plan = {
        o: settings(len(ts), methods, noises, ablations, worlds, k_ablation, repeats) for o, ts in by_object.items()
    }
    total = sum(max(t.frames for t in by_object[o]) * sum(s.worlds for s in p) for o, p in plan.items())
    bar = progress_bar(total, "tracking", unit="world-frames", disable=quiet)
    results: list[TrackResult] = []
    for o, ts in by_object.items():
        drift = open_loop_disagreement(ts, device, {"substeps": substeps, **(population or {})})
        first = len(results)
        by_k: dict[int, list[TrackSetting]] = {}
        for s in plan[o]:
            by_k.setdefault(s.worlds, []).append(s)
        for k, k_tracks in by_k.items():  # the frames of one population advance all its groups at once
            t1 = time.perf_counter()
            results += run_tracks(ts, k_tracks, device, suite.seed, bar.update, substeps, config, population,
                                  observations, vision_sigma)  # fmt: skip
            for r in results[first:]:
                r.open_loop = drift[: r.add.shape[0], r.setting.trajectory]
            frames = max(t.frames for t in ts)
            seconds = time.perf_counter() - t1
            log.info(
                f"tracked {o}: {len(k_tracks)} tracks x {k} worlds, {frames} frames in {seconds:.0f} s"
                f" ({1e3 * seconds / frames:.1f} ms per frame)"
            )
            if checkpoint:  # what is done so far survives a run cut short (a time limit)
                checkpoint(
                    _collect(
                        suite,
                        results,
                        worlds,
                        k_ablation,
                        t_truth,
                        time.perf_counter() - t0,
                        device,
                        substeps,
                        config,
                        population,
                        vision,
                    )
                )
    bar.close()
    t_track = time.perf_counter() - t0 - t_truth
    if frames_to is not None:
        save_frames(results, frames_to)
    return _collect(suite, results, worlds, k_ablation, t_truth, t_track, device, substeps, config, population, vision)


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


def _collect(
    suite: Suite,
    results: list[TrackResult],
    worlds: int,
    k_ablation: Sequence[int],
    t_truth: float,
    t_track: float,
    device: str,
    substeps: int = PopulationConfig.substeps,
    config: TrackerConfig | None = None,
    population: dict[str, int | float | bool] | None = None,
    vision: dict | None = None,
) -> dict:
    """ADD statistics over tracks: mean of per-track mean ADD, its std over tracks, and the max
    over all frames, per method and noise level (Fig. 2) and per ablation setting (Fig. 3)."""
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
    return {
        "suite": asdict(suite),
        "device": device,
        "worlds": worlds,
        "repeats": 1 + max((r.setting.repeat for r in results), default=0),
        "tracker": _changed(asdict(config or TrackerConfig()), asdict(TrackerConfig())),
        "substeps": substeps,
        "population": dict(population or {}),
        "observations": vision or {"schedule": "none"},
        "seconds": {"ground_truth": t_truth, "tracking": t_track},
        "summary": fig2,
        "summary_best_world": best_world,
        "ablations": ablation,
        "tracks": [r.summary() | _per_frame(r) for r in results],
    }


def _changed(config: dict, default: dict) -> dict:
    """The settings of ``config`` that differ from ``default``, nested ones as ``outer.inner``."""
    out = {}
    for key, value in config.items():
        if isinstance(value, dict):
            out |= {f"{key}.{k}": v for k, v in _changed(value, default[key]).items()}
        elif key != "seed" and value != default[key]:
            out[key] = value
    return out
