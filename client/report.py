"""The robot side's replay report: a trajectory file or a session recording streamed to the
service through a client, and what came back (``inhand-tracker replay``)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from inhand_tracker.protocol import SessionRecording, SessionStatus, Trajectory
from inhand_tracker.protocol.recording import is_recording

from .replay import NOISE_LEVELS, ReplayResult, noisy_start
from .replay import replay as stream
from .tracker_client import TrackerClient

__all__ = ["Scorer", "replay_file"]

UNREACHABLE = 5
"""The exit status of a replay that found no service, as ``watch``'s (docs/operations.md)."""
_PROGRESS_S = 10.0
"""How often a replay whose output is not a terminal says how far it got [s]."""

Scorer = Callable[[str, np.ndarray, np.ndarray], np.ndarray]
"""ADD per frame [m] of an object (by its catalog name) at its true poses (N, 7) against the
estimates (N, 7); a ValueError when it does not know the object. The service's install has one
(its object catalog and metric); the robot side alone reports the position error instead."""


def replay_file(
    client: TrackerClient,
    file: Path,
    method: str | None = None,
    worlds: int | None = None,
    rate: float = 0.0,
    noise: str = "med",
    live: bool = False,
    say: Callable[[str], None] = print,
    score: Scorer | None = None,
    allow_fewer: bool = False,
) -> int:
    """Stream a trajectory file (``.traj``) or a session recording (its folder or ``.mcap``) to the service as
    its robot would, and report what came back: latency, and ADD where the file carries the
    truth. A recording reopens its session as it was opened, unless ``method`` or ``worlds``
    say otherwise; a trajectory starts from its true pose with ``noise`` (low, med, high).
    ``score``: ADD against the truth (:data:`Scorer`), else the position error is reported.
    Returns the exit status; a bad argument is a ValueError naming it."""
    traj, recording, start = _load(file, noise)
    chosen = {k: v for k, v in {"method": method, "worlds": worlds}.items() if v is not None}
    chosen["allow_fewer"] = allow_fewer
    if recording is not None:  # the session as it was opened, unless told otherwise
        o = recording.opened
        chosen = {"method": o["method"], "worlds": o["worlds"], "overrides": o["overrides"], **chosen}
    try:
        client.wait_ready(client.open_timeout, absent=3.0, waiting=_waiting(say))
        info = client.open_session(traj.robot, traj.object, **start, **chosen)
        say(
            f"session {info.session}: {traj.object} in {traj.robot}, {info.worlds} worlds, {info.method}; "
            f"{traj.frames} frames of '{traj.name}'"
        )
        errors: list[float] = []

        said = [time.monotonic()]

        def show(i: int, est) -> None:
            if not live and time.monotonic() - said[0] >= _PROGRESS_S:  # a log, not a terminal: a line now and then
                said[0] = time.monotonic()
                say(f"  frame {i + 1}/{traj.frames}, {est.status}, latency {est.latency_ms:.1f} ms")
            if traj.truth is None:
                return
            errors.append(float(np.linalg.norm(traj.truth.pose[i, :3] - est.pose[:3])))
            if live and (i % 15 == 0 or i == traj.frames - 1):
                print(
                    f"\r  frame {i + 1:4d}/{traj.frames}  {est.status:10s} position error {errors[-1] * 1e3:6.1f} mm"
                    f"  latency {est.latency_ms:5.1f} ms",
                    end="",
                    flush=True,
                )

        result = stream(client, traj, rate=rate, on_estimate=show)
        if live:
            print()
        _latency(result, client.status(), say)
        if traj.truth is not None:
            _summary(traj, result.estimates, say, score)
        if recording is not None and recording.estimates:
            was = {e.seq: e.pose[:3] for e in recording.estimates}
            moved = [float(np.linalg.norm(e.pose[:3] - was[e.seq])) for e in result.estimates if e.seq in was]
            most = max(moved, default=0.0) * 1e3
            say(f"against the recording: {len(moved)} estimates, position differs by at most {most:.3f} mm")
        client.close_session()
    except Exception as exc:  # a user's command: say what went wrong, no traceback
        print(f"replay: {type(exc).__name__}: {exc}", file=sys.stderr)
        return UNREACHABLE if isinstance(exc, TimeoutError) and "does not answer" in str(exc) else 1
    return 0


def _waiting(say: Callable[[str], None]) -> Callable[[float], None]:
    """Say that the service answers but is not ready (a first start compiles for minutes), then
    every half minute how long it has been."""
    said = [-1.0]

    def waiting(seconds: float) -> None:
        if said[0] < 0 or seconds - said[0] >= 30:
            say(f"waiting for the service to be ready (compiling its kernels): {seconds:.0f} s")
            said[0] = seconds

    return waiting


def _load(file: Path, noise: str) -> tuple[Trajectory, SessionRecording | None, dict]:
    """The file's trajectory, its recording (a ``.mcap``'s), and where the session starts: as the
    recorded session was opened, or from the true pose with ``noise``."""
    if noise not in NOISE_LEVELS:
        raise ValueError(f"--noise: expected low, med or high, got '{noise}'")
    recording = None
    try:
        if is_recording(file):
            recording = SessionRecording.load(file)
            traj = recording.trajectory
        else:
            traj = Trajectory.load(file)
    except (OSError, ValueError) as exc:
        raise ValueError(f"replay: {exc}") from None
    if recording is not None:
        o = recording.opened
        return traj, recording, {"p0": o["p0"], "sigma_t": o["sigma_t"], "sigma_r": o["sigma_r"], "q0": o["q0"]}
    sigma_t, sigma_r = NOISE_LEVELS[noise]
    start = {"p0": noisy_start(traj, sigma_t, sigma_r), "sigma_t": sigma_t, "sigma_r": sigma_r}
    start["q0"] = traj.truth.initial_q if traj.truth else None
    return traj, None, start


def _latency(result: ReplayResult, status: SessionStatus, say: Callable[[str], None]) -> None:
    """What the service and the client measured of a replay's frames and latency."""
    dropped = status.duplicates + status.late + status.stale
    say(
        f"estimates: {len(result.estimates)}; gaps {status.gaps}, dropped {dropped}"
        f" (duplicate {status.duplicates}, late {status.late}, stale {status.stale})"
    )
    say(
        f"latency, frame received to estimate ready (service): p50 {status.latency_p50_ms:.1f} ms, "
        f"p99 {status.latency_p99_ms:.1f} ms"
    )
    if result.round_trip_ms:
        rt = np.asarray(result.round_trip_ms)
        say(
            f"latency, frame put to estimate received (client): p50 {np.percentile(rt, 50):.1f} ms, "
            f"p99 {np.percentile(rt, 99):.1f} ms"
        )
    if status.joints_off:  # the model check: the robot config's servos are not the robot's
        off = ", ".join(f"{name} {rms * 1e3:.0f}" for name, rms in status.joints_off.items())
        say(f"model check: joints the worlds hold away from the robot's (RMS, mrad or mm): {off}; see `calibrate`")


def _summary(traj: Trajectory, estimates: list, say: Callable[[str], None], score: Scorer | None) -> None:
    """ADD against the ground truth where ``score`` knows the object, else the position error."""
    seqs = np.array([e.seq for e in estimates])
    try:
        if score is None:
            raise ValueError("no scorer")
        add = score(traj.object, traj.truth.pose[seqs], np.stack([e.pose for e in estimates]))
    except ValueError:
        err = [float(np.linalg.norm(traj.truth.pose[e.seq, :3] - e.pose[:3])) for e in estimates]
        say(f"position error: mean {np.mean(err) * 1e3:.2f} mm, max {np.max(err) * 1e3:.2f} mm")
        return
    say(
        f"ADD over {len(add)} frames: mean {add.mean() * 1e3:.2f} mm, median {np.median(add) * 1e3:.2f} mm, "
        f"max {add.max() * 1e3:.2f} mm"
    )
