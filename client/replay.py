"""Replay a trajectory file through a :class:`TrackerClient`, as a robot would stream it."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from inhand_tracker.protocol import Estimate, Trajectory

from .tracker_client import TrackerClient

__all__ = ["NOISE_LEVELS", "ReplayResult", "noisy_start", "replay"]

NOISE_LEVELS: dict[str, tuple[float, float]] = {"low": (0.001, 0.01), "med": (0.005, 0.1), "high": (0.01, 1.0)}
"""Initial pose noise (Sigma_p) per level, as the paper's: translation [m], rotation [rad]."""


@dataclass
class ReplayResult:
    estimates: list[Estimate]
    """The estimates received, in seq order."""
    round_trip_ms: list[float]
    """Per frame, from the frame's put to its estimate's arrival [ms] (lock-step replays only)."""


def noisy_start(trajectory: Trajectory, sigma_t: float, sigma_r: float, seed: int = 0) -> np.ndarray:
    """The true initial pose with Gaussian noise (translation [m], rotation vector [rad]): the
    "vision" estimate a benchmark hands the tracker. Needs the trajectory's ground truth."""
    if trajectory.truth is None:
        raise ValueError(f"trajectory '{trajectory.name}' has no ground truth to start from; give p0")
    rng = np.random.default_rng(seed)
    pose = np.asarray(trajectory.truth.initial_pose, np.float64).copy()
    pose[:3] += rng.normal(0.0, sigma_t, 3)
    omega = rng.normal(0.0, sigma_r, 3)
    angle = np.linalg.norm(omega)
    axis = omega / angle if angle > 0 else np.zeros(3)
    dq = np.concatenate([axis * np.sin(angle / 2), [np.cos(angle / 2)]])
    x1, y1, z1, w1 = pose[3:]
    x2, y2, z2, w2 = dq  # q * dq: the noise in the object's frame, as the service samples it
    pose[3:] = [
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    ]
    return pose.astype(np.float32)


def replay(
    client: TrackerClient,
    trajectory: Trajectory,
    rate: float = 0.0,
    on_estimate: Callable[[int, Estimate], None] | None = None,
    timeout: float = 60.0,
) -> ReplayResult:
    """Send every frame of ``trajectory`` on the open session and collect the estimates.

    ``rate`` [Hz] paces the frames like a robot's control loop; 0 sends each frame when the
    estimate of the previous one has arrived (as fast as the service tracks, lock-step).
    """
    if client.info is None:
        raise RuntimeError("open a session before replaying")
    estimates: list[Estimate] = []
    round_trips: list[float] = []
    paced: list[Estimate] = []
    if rate > 0:
        client.on_pose(paced.append)
    t0 = time.perf_counter()
    try:
        for i in range(trajectory.frames):
            if rate > 0:
                time.sleep(max(0.0, t0 + i / rate - time.perf_counter()))
            sent = time.perf_counter()
            client.send(trajectory.frame(i, client.info.session, seq=i))
            if rate <= 0:
                estimates.append(client.latest_pose(timeout=timeout, after_seq=i))
                round_trips.append((time.perf_counter() - sent) * 1e3)
                if on_estimate:
                    on_estimate(i, estimates[-1])
        if rate > 0:
            client.latest_pose(timeout=timeout, after_seq=trajectory.frames - 1)
            estimates = sorted(paced, key=lambda e: e.seq)
    finally:
        if rate > 0:
            client.remove_pose_callback(paced.append)
    return ReplayResult(estimates, round_trips)
