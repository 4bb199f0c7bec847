"""`inhand-tracker bench speed`: the whole tracker frame (frame in, estimate out) against the
physics alone, per population size, on a recorded pick and place (the hand in motion, not a held
pose: the solver works hardest there)."""

from __future__ import annotations

import itertools
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np
import warp as wp

from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.paths import DATA_DIR
from inhand_tracker.service.tracker import Frame, Tracker, TrackerConfig
from inhand_tracker.sim_backend import HandSpec, Population, PopulationConfig, catalog_object, resolve_device

from .publish import SPEED_COLUMNS, speed_rows
from .sim import release_memory, used_bytes

__all__ = ["REAL_TIME_MS", "SpeedResult", "as_dicts", "bench_speed", "format_table"]

REAL_TIME_MS = 1e3 / 30.0
"""A 30 Hz robot sends a frame every 33.3 ms."""
TRAJECTORY = "smoke-foam_brick_pick_place_0.traj"


@dataclass(frozen=True)
class SpeedResult:
    device: str
    worlds: int
    """W, all worlds of the population."""
    groups: int
    """G, sessions sharing the population; each tracks with K = W / G worlds."""
    substeps: int
    solver: str
    iterations: int
    """The solver's iteration cap per substep."""
    ls_iterations: int
    """Its line-search cap."""
    tolerance: float
    """The solver's convergence tolerance."""
    ls_tolerance: float
    """Its line search's."""
    frames: int
    """Timed frames (after the warm-up, which includes the graph captures)."""
    tracker_median_ms: float
    tracker_p99_ms: float
    physics_median_ms: float
    physics_p99_ms: float
    bytes_per_world: float
    captured: bool
    """Whether the frame ran as one captured graph (CUDA) or as plain calls around a physics graph (CPU)."""

    @property
    def ratio(self) -> float:
        """Tracker over physics, medians."""
        return self.tracker_median_ms / self.physics_median_ms

    @property
    def world_substeps_per_s(self) -> float:
        """Physics throughput of the whole tracker frame: worlds x substeps per second (median)."""
        return self.worlds * self.substeps / (self.tracker_median_ms / 1e3)

    @property
    def real_time(self) -> bool:
        """p99 within a 30 Hz frame."""
        return self.tracker_p99_ms <= REAL_TIME_MS


def _frames(traj: Trajectory, groups: int) -> list[Frame]:
    tile = lambda a: np.repeat(a[:, None], groups, axis=1)  # noqa: E731 - every group replays the same robot
    fields = {n: tile(v) for n, v in traj.sensing.items() if v is not None}
    return [Frame(**{n: v[f] for n, v in fields.items()}) for f in range(traj.frames)]


def _timed(fn, frames: list, sync) -> np.ndarray:
    times = np.empty(len(frames))
    for i, frame in enumerate(frames):
        t = time.perf_counter()
        fn(frame)
        sync()
        times[i] = (time.perf_counter() - t) * 1e3
    return times


def bench_speed(
    worlds: list[int],
    groups: list[int],
    substeps: list[int],
    *,
    frames: int = 200,
    warmup: int = 30,
    device: str = "auto",
    jacobians: Sequence[str] = (PopulationConfig.jacobian,),
    caps: Sequence[tuple[int | None, int | None]] = ((None, None),),
    physics: Mapping[str, object] | None = None,
    progress=None,
) -> list[SpeedResult]:
    """Time ``frames`` tracker steps and as many bare physics frames for every (substeps,
    solver caps (iterations, line-search iterations; None: the solver's own), Jacobian layout,
    G, W). ``physics`` overrides further :class:`PopulationConfig` fields (tolerance, ...) in every row."""
    overrides = dict(physics or {})
    dev = resolve_device(device)
    traj = Trajectory.load(DATA_DIR / TRAJECTORY)
    obj = catalog_object(traj.object)
    if warmup + frames > traj.frames:
        raise ValueError(f"frames: at most {traj.frames - warmup} after {warmup} warm-up frames, got {frames}")
    for w in worlds:
        for g in groups:
            if w % g:
                raise ValueError(f"worlds: {w} do not split into {g} groups")
    for jacobian in jacobians:
        PopulationConfig(jacobian=jacobian, **overrides)  # a bad value fails before anything is measured
    sync = (lambda: wp.synchronize_device(dev)) if dev.is_cuda else (lambda: None)
    results = []
    for n, (iterations, ls_iterations), jacobian, g in itertools.product(substeps, caps, jacobians, groups):
        recorded = _frames(traj, g)
        p0 = np.repeat(traj.truth.initial_pose[None], g, axis=0)
        q0 = np.repeat(traj.truth.initial_q[None], g, axis=0)
        for w in worlds:
            config = PopulationConfig(
                groups=g, worlds=w // g, substeps=n, device=dev.alias, jacobian=jacobian,
                iterations=iterations, ls_iterations=ls_iterations, **overrides,
            )  # fmt: skip
            results.append(_measure(config, obj, recorded, (p0, q0), warmup, frames, sync))
            if progress:
                progress(results[-1])
            release_memory(dev)
    return results


def _measure(
    config: PopulationConfig, obj, recorded: list, start: tuple, warmup: int, frames: int, sync
) -> SpeedResult:
    """One row: ``frames`` tracker steps of a population of ``config`` after ``warmup``, then the
    same motion again with nothing but the physics graph; ``start`` is the initial (p0, q0)."""
    dev = resolve_device(config.device)
    sync()
    before = used_bytes(dev)
    pop = Population(HandSpec(), obj, config)
    tracker = Tracker(pop, TrackerConfig())
    tracker.start(*start)
    for frame in recorded[:warmup]:
        tracker.step(frame)
    timed = recorded[warmup : warmup + frames]
    track = _timed(tracker.step, timed, sync)
    used = used_bytes(dev) - before
    tracker.start(*start)
    for frame in recorded[:warmup]:
        pop.set_targets(frame.controls)
        pop.step()
    physics = np.empty(len(timed))
    for i, frame in enumerate(timed):
        pop.set_targets(frame.controls)
        sync()
        t = time.perf_counter()
        pop.step()
        sync()
        physics[i] = (time.perf_counter() - t) * 1e3
    s = config.solver_settings
    return SpeedResult(
        device=dev.alias,
        worlds=config.world_count,
        groups=config.groups,
        substeps=config.substeps,
        solver=s.name,
        iterations=s.iterations,
        ls_iterations=s.ls_iterations,
        tolerance=config.tolerance,
        ls_tolerance=config.ls_tolerance,
        frames=len(timed),
        tracker_median_ms=float(np.median(track)),
        tracker_p99_ms=float(np.percentile(track, 99)),
        physics_median_ms=float(np.median(physics)),
        physics_p99_ms=float(np.percentile(physics, 99)),
        bytes_per_world=used / config.world_count,
        captured=tracker.captured,
    )


def format_table(results: list[SpeedResult]) -> str:
    lines = ["| " + " | ".join(SPEED_COLUMNS) + " |", "|" + "---|" * len(SPEED_COLUMNS)]
    lines += ["| " + " | ".join(str(v) for v in row) + " |" for row in speed_rows(as_dicts(results))]
    return "\n".join(lines)


def as_dicts(results: list[SpeedResult]) -> list[dict]:
    return [
        {**asdict(r), "ratio": r.ratio, "world_substeps_per_s": r.world_substeps_per_s, "real_time": r.real_time}
        for r in results
    ]
