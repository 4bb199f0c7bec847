"""The tracks of an accuracy run: what each group of a batched population does, how it is fed a
recording frame by frame, and how its estimates score against the truth (ADD, ADD-S, coverage of
the reported region, the track state)."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from inhand_tracker.protocol import DEFAULT_WORLDS, TrackState, Trajectory
from inhand_tracker.service.evaluation import add_error, adds_error, pose_error, within_region
from inhand_tracker.service.tracker import Frame, Tracker
from inhand_tracker.service.tracker.cost import TERMS
from inhand_tracker.service.tracker.sampling import sample_poses
from inhand_tracker.sim_backend import Population, PopulationConfig, catalog_object

from .recorder import Recording
from .run import AccuracyRun
from .suites import EXPLORATION, K_ABLATION, NOISE_LEVELS, robot_spec

__all__ = ["TrackResult", "TrackSetting", "per_frame", "plan_tracks", "run_tracks", "save_frames"]

_ADDS_EVERY = 10
_KEPT = ("cost", "lost", "separation", "evidence", "reckoning")
"""What :func:`_follow` said per frame that a track keeps beside its errors."""
"""ADD-S is scored on every tenth frame (a nearest-point search per surface point)."""

_CONTACT_TERMS = (3, 4, 5, 10, 11)  # fingertips: contact, force magnitude, direction; touch zones: contact, force
_SLIP_TERMS = (6, 7, 8, 9)


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
    """Frames after which the tracker re-seeded the group (never for OLP, the pure open loop)."""
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
    (F,) the lowest window cost, ``lost`` (F,) the share of worlds that lost the object,
    ``separation`` (F,) and ``evidence`` (F,) the last update's F ratio and strength, ``reckoning``
    (F,) how far the pose was the open-loop world's."""

    def evidence(self) -> dict[str, float]:
        """The median over the track's updates of their separation F ratio and strength (after the
        first update), and the mean over its frames of how far the pose was the open-loop world's
        (empty where the frames were not kept)."""
        if not self.frames or "separation" not in self.frames:
            return {}
        f, s = self.frames["separation"], self.frames["evidence"]
        after = np.flatnonzero(f > 0)
        if after.size == 0:
            return {}
        first = after[0]
        return {
            "separation_median": float(np.median(f[first:])),
            "evidence_median": float(np.median(s[first:])),
        } | ({"reckoning_mean": float(np.mean(self.frames["reckoning"]))} if "reckoning" in self.frames else {})

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
    said the model's contacts were wrong (:attr:`ContactExploration.contact_gate_cost`)."""
    servo_strength: dict[str, float] | None = None
    """Where the tracker explored its servos: each chain's strength factor on the config's at the
    track's end, the estimate's weighted mean (:class:`.ServoExploration`)."""
    open_loop: np.ndarray | None = field(default=None, repr=False)
    """ADD of the tracker's physics run open loop from the true start with the true mass and
    friction, per frame, (F,) [m]: how far the engines disagree about this track's motion."""

    open_loop_force_ratio: float | None = None
    """How hard the tracker's hand presses in that open-loop run against the truth's: summed
    touch-zone (or fingertip) force over the true one."""

    def summary(self) -> dict:
        return {
            **asdict(self.setting),
            "trajectory": self.trajectory,
            "object": self.object,
            "add_mean_mm": float(self.add.mean() * 1e3),
            "add_max_mm": float(self.add.max() * 1e3),
            "best_world_add_mean_mm": float(self.add_best.mean() * 1e3),
            "diverged_frames": self.diverged,
            **self.evidence(),
            **({} if self.contacts_explored is None else {"contacts_explored": self.contacts_explored}),
            **({} if self.servo_strength is None else {"servo_strength": self.servo_strength}),
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
                    "open_loop_force_ratio": self.open_loop_force_ratio,
                    "open_loop_max_mm": float(self.open_loop.max() * 1e3),
                }
            ),
        }


def plan_tracks(
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
    run: AccuracyRun,
    progress: Callable[[int], None] | None = None,
) -> list[TrackResult]:
    """Run ``tracks`` on ``trajectories`` of one object: one population per world count, every
    track a group of it. The noisy initial pose of a (trajectory, noise) pair is the same for
    every method, so methods are compared on equal footing; each repeat draws its own."""
    obj = catalog_object(trajectories[0].object)
    spec = run.robot or robot_spec(trajectories[0].robot)
    spec = replace(spec, servos=run.servos) if run.servos else spec
    rec = Recording.stack(trajectories)
    gen = torch.Generator().manual_seed(run.suite.seed)
    start = torch.tensor(rec.initial_pose, dtype=torch.float32)
    # The "vision" estimates, per noise level and repeat; repeat 0 draws what a single run always drew.
    repeats = max(t.repeat for t in tracks) + 1
    p0 = {(n, r): _noisy(start, *NOISE_LEVELS[n], gen) for r in range(repeats) for n in NOISE_LEVELS}
    points = obj.surface_points(1000)
    events = [int(x) if (x := t.meta.get("drop_frame")) is not None else None for t in trajectories]
    results: list[TrackResult] = []
    for k in sorted({t.worlds for t in tracks}):
        group = [t for t in tracks if t.worlds == k]
        rows = np.array([t.trajectory for t in group])
        tracker = _tracker(spec, obj, group, k, run)
        tracker.start(
            np.stack([p0[t.noise, t.repeat][t.trajectory] for t in group]),
            rec.initial_q[rows],
            sigma_t=np.array([NOISE_LEVELS[t.noise][0] for t in group]),
            sigma_r=np.array([NOISE_LEVELS[t.noise][1] for t in group]),
        )
        tick = functools.partial(progress, len(group) * k) if progress else None
        said = _follow(tracker, rec, rows, run, tick)
        results += _score(said, rec, group, rows, obj.name, points, events)
    return results


def _tracker(spec, obj, group: Sequence[TrackSetting], k: int, run: AccuracyRun) -> Tracker:
    """A tracker whose groups are ``group``'s tracks, in a population of ``k`` worlds each."""
    physics = PopulationConfig(groups=len(group), worlds=k, device=run.device, **run.physics)
    pop = Population(spec, obj, physics)
    terms = np.ones((len(group), TERMS), bool)
    for g, t in enumerate(group):
        terms[g, list(_CONTACT_TERMS)] = t.contact_terms
        terms[g, list(_SLIP_TERMS)] = t.slip_terms
    return Tracker(
        pop,
        replace(run.config, seed=run.suite.seed),
        methods=[t.method for t in group],
        exploration=[EXPLORATION[t.exploration] for t in group],
        terms=terms,
    )


def _follow(
    tracker: Tracker, rec: Recording, rows: np.ndarray, run: AccuracyRun, tick: Callable[[], None] | None
) -> dict[str, np.ndarray]:
    """Feed the trajectories ``rows`` (one per group) to ``tracker`` frame by frame, with a
    camera's noisy pose where ``run.observations`` says; what the estimates said, per frame and
    group: ``pose``, ``best_pose``, ``covariance``, ``status``, ``cost``, ``lost``, and per group
    ``diverged`` (frames), ``explored`` (contacts, at the end) and ``servos`` (strengths by chain
    name, (G,) each, at the end; empty without servo exploration)."""
    frames, groups = rec.frames, len(rows)
    said = {
        "pose": np.empty((frames, groups, 7), np.float32),
        "best_pose": np.empty((frames, groups, 7), np.float32),
        "covariance": np.empty((frames, groups, 6, 6), np.float32),
        "status": np.empty((frames, groups), np.int64),
        "cost": np.empty((frames, groups), np.float32),
        "lost": np.empty((frames, groups), np.float32),
        "separation": np.empty((frames, groups), np.float32),
        "evidence": np.empty((frames, groups), np.float32),
        "reckoning": np.empty((frames, groups), np.float32),
    }
    diverged = np.zeros(groups, np.int64)
    seen = _observed(rec, run.observations)[:, rows]  # (F, G)
    vision = torch.Generator().manual_seed(run.suite.seed + 1)
    cov = np.diag([run.vision_sigma[0] ** 2] * 3 + [run.vision_sigma[1] ** 2] * 3)
    for f in range(frames):
        est = tracker.step(Frame(**{name: None if v is None else v[f, rows] for name, v in rec.sensing.items()}))
        for name, series in said.items():
            series[f] = getattr(est, name)
        diverged += est.reseeded
        for g in np.flatnonzero(seen[f]):
            noisy = _noisy(torch.tensor(rec.object_pose[f, rows[g]][None]), *run.vision_sigma, vision)[0]
            tracker.observe(int(g), noisy, cov)
        if tick:
            tick()
    servos = tracker.servos.strengths(tracker.weights()) if tracker.servos.enabled else {}
    servos = {name: value.cpu().numpy() for name, value in servos.items()}
    return {**said, "diverged": diverged, "explored": est.contacts_explored, "servos": servos}


def _score(
    said: dict[str, np.ndarray],
    rec: Recording,
    group: Sequence[TrackSetting],
    rows: np.ndarray,
    obj: str,
    points: np.ndarray,
    events: list[int | None],
) -> list[TrackResult]:
    """Each track's errors against the truth, from what the estimates ``said`` (:func:`_follow`)."""
    truth, poses, covariances = rec.object_pose[:, rows], said["pose"], said["covariance"]
    add = add_error(points, truth, poses)  # (F, G)
    add_best = add_error(points, truth, said["best_pose"])
    add_s = adds_error(points[:200], truth[::_ADDS_EVERY], poses[::_ADDS_EVERY])
    error = pose_error(truth, poses)
    inside = within_region(error, covariances)
    error = error.astype(np.float32)
    out = []
    for g, t in enumerate(group):
        n = int(rec.lengths[t.trajectory])
        frames = {"error": error, "covariance": covariances} | {k: said[k] for k in _KEPT}
        frames = {k: v[:n, g] for k, v in frames.items()}
        out.append(
            TrackResult(t, rec.names[t.trajectory], obj, add[:n, g], add_best[:n, g], int(said["diverged"][g]),
                        add_s[: -(-n // _ADDS_EVERY), g], inside[:n, g], said["status"][:n, g],
                        events[t.trajectory], frames, bool(said["explored"][g]),
                        {n: round(float(v[g]), 3) for n, v in said["servos"].items()} or None)
        )  # fmt: skip
    return out


def per_frame(r: TrackResult) -> dict:
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
