"""The service's frame budget: how long one step of a population takes on this device, as a
function of its worlds, and so how many worlds a new session may have while the service still
keeps up with its robots.

A step's time is learnt, not assumed: measured at start-up (a population replaying the bundled
pick and place, the hand in contact, at two sizes), cached per device and physics setting, and
corrected online from every population's own steps.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inhand_tracker.service.paths import DATA_DIR

__all__ = [
    "HOLD",
    "STEP_TIME_MOTION",
    "FrameTimes",
    "affordable_worlds",
    "device_name",
    "ladder",
    "measure_step_times",
]

STEP_TIME_MOTION = DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
"""What the frame times are measured on: a pick and place, the hand in contact for most of it."""

log = logging.getLogger(__name__)


HOLD = 0.15
"""How near the budget [share] a step time may lie for ``auto`` to keep the K it granted before."""


def ladder(smallest: int, largest: int) -> list[int]:
    """The K a budget grants, powers of two from ``smallest`` to ``largest``: few sizes, because on
    CUDA every new population size compiles its own collision kernels the first time (tens of
    seconds), and a doubling is the finest step that changes accuracy measurably."""
    out, k = [], 1
    while k <= largest:
        if k >= smallest:
            out.append(k)
        k *= 2
    return out


def device_name(device) -> str:
    """What the frame times are cached by: the GPU's model, or the CPU's model and core count."""
    if device.is_cuda:
        import warp as wp

        return wp.get_device(device.alias).name
    cpu = platform.processor() or platform.machine()
    try:  # Linux names its CPU here; platform.processor() is often empty there
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    return f"{cpu} x{os.cpu_count()}"


@dataclass
class FrameTimes:
    """The p99 time of one step of a population [ms] by its worlds W, on one device and physics
    setting: measured points, made non-decreasing in W (a busy machine can time a larger
    population faster than a smaller one; more worlds never cost less), linear between them, flat
    below the smallest (a GPU's launch cost does not shrink with fewer worlds), and above the
    largest the greater of the last segment's growth and proportional growth: past what was
    measured, admission assumes the worst a device does."""

    key: dict
    """The device and the physics settings the points hold for."""
    points: dict[int, float] = field(default_factory=dict)
    """W -> p99 step time [ms]."""
    measured: str = ""
    """When the points were last changed (ISO date, UTC)."""
    granted: dict[str, int] = field(default_factory=dict)
    """The K ``auto`` last granted each kind of population (robot, object, overrides), kept across
    starts so that the same open gets the same K while the step times stay near (:data:`HOLD`)."""

    def predict(self, worlds: int) -> float:
        if not self.points:
            return 0.0
        w = np.array(sorted(self.points), dtype=np.float64)
        t = np.maximum.accumulate(np.array([self.points[int(x)] for x in w]))
        if worlds <= w[-1]:
            return float(np.interp(worlds, w, t))
        proportional = t[-1] * worlds / w[-1]
        if len(w) == 1:
            return float(proportional)
        slope = (t[-1] - t[-2]) / (w[-1] - w[-2])
        return float(max(t[-1] + slope * (worlds - w[-1]), proportional))

    def observe(self, worlds: int, p99_ms: float, weight: float = 0.25) -> None:
        """A population of ``worlds`` measured at ``p99_ms``: a new point, or an old one moved by
        ``weight`` of the way there (one busy second should not swing admission)."""
        old = self.points.get(worlds)
        self.points[worlds] = p99_ms if old is None else old + weight * (p99_ms - old)
        self.measured = time.strftime("%Y-%m-%d", time.gmtime())

    # ------------------------------------------------------------------ the cache
    @staticmethod
    def path(directory: Path, key: dict) -> Path:
        digest = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
        return Path(directory).expanduser() / f"frame-times-{digest}.json"

    @classmethod
    def load(cls, directory: Path, key: dict) -> FrameTimes:
        """The cached points for ``key``, or none (a missing or unreadable file is a cold start)."""
        path = cls.path(directory, key)
        try:
            data = json.loads(path.read_text())
            if data["key"] == key:
                points = {int(w): float(t) for w, t in data["points"].items()}
                granted = {str(k): int(v) for k, v in data.get("granted", {}).items()}
                return cls(key, points, data.get("measured", ""), granted)
        except FileNotFoundError:
            pass
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("frame times: ignoring the unreadable cache %s (%s)", path, exc)
        return cls(key)

    def save(self, directory: Path) -> None:
        path = self.path(directory, self.key)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp")
            points = {str(w): round(t, 3) for w, t in sorted(self.points.items())}
            data = {"key": self.key, "points": points, "measured": self.measured, "granted": self.granted}
            tmp.write_text(json.dumps(data, indent=1))
            tmp.replace(path)
        except OSError as exc:  # a read-only home costs a measurement per start, not the service
            log.warning("frame times: cannot write the cache %s (%s)", path, exc)


def affordable_worlds(
    times: FrameTimes,
    load_ms: float,
    budget_ms: float,
    groups: int,
    sizes: list[int],
    at_most: int,
    previous: int | None = None,
) -> int:
    """The largest K of ``sizes`` (at most ``at_most``) whose population of ``groups`` x K worlds
    fits in the budget beside ``load_ms`` of populations already stepping; 0 when none does.

    ``previous``, the K the same kind of population got before on an idle service, is kept while
    the choice between it and the new one lies within :data:`HOLD` of the budget: step times
    measured again move by a few per cent from one start to the next, and a session should not get
    half or twice the worlds (and track differently) for that. Beside other populations (``load_ms``)
    the K is what fits: theirs is a real change."""
    predict = lambda k: load_ms + times.predict(groups * k)  # noqa: E731
    best = max((k for k in sizes if k <= at_most and predict(k) <= budget_ms), default=0)
    if previous and previous != best and previous in sizes and previous <= at_most and load_ms == 0:
        shrinks_by_a_little = previous > best and predict(previous) <= budget_ms * (1 + HOLD)
        grows_by_a_little = previous < best and predict(best) > budget_ms * (1 - HOLD)
        if shrinks_by_a_little or grows_by_a_little:
            return previous
    return best


def measure_step_times(tracker, traj, q0: np.ndarray, rest: np.ndarray, frames: int = 120) -> float:
    """The p99 of a tracker's steps [ms] over ``frames`` of the trajectory ``traj`` replayed in every
    group (the first third untimed: the hand reaches the object), or, with ``traj`` None, holding
    the joints ``q0`` (D,) with the object at ``rest`` (7,)."""
    from inhand_tracker.service.tracker import Frame  # torch: only where a service measures

    g = tracker.G
    tile = lambda a: np.repeat(np.asarray(a, np.float32)[None], g, axis=0)  # noqa: E731
    if traj is None:
        pose = rest
        sensing = [{"controls": tile(q0), "q": tile(q0)}] * frames
    else:
        pose, frames = traj.truth.initial_pose, min(frames, traj.frames)
        sensing = [{n: tile(v[f]) for n, v in traj.sensing.items() if v is not None} for f in range(frames)]
    tracker.start(tile(pose), sensing[0]["q"])
    times = []
    for fields in sensing:
        began = time.perf_counter()
        tracker.step(Frame(**fields))
        times.append((time.perf_counter() - began) * 1e3)
    return float(np.percentile(times[frames // 3 :], 99))
