"""The service under load: N robots, each streaming a bundled trajectory at a fixed rate through
its own client to a service embedded on loopback (real Zenoh sessions), and what each got back:
estimates per second, latency (arrival at the service to estimate) p50 and p99, and the frames
the service counted late, stale (dropped under overload) or skipped. A long run is a soak: the
process's resident memory a tenth of the way in and at the end says whether anything grows.
With churn, another peer opens and closes sessions all the while, each with settings no
population has, so that every open it gets through builds a population beside the robots'."""

from __future__ import annotations

import contextlib
import resource
import socket
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from inhand_tracker.client import TrackerClient, TrackerError
from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.paths import DATA_DIR
from inhand_tracker.service.server import ServiceConfig, TrackerNode

__all__ = ["LoadResult", "as_dicts", "bench_load", "format_table"]


@dataclass
class LoadResult:
    session: int
    worlds: int
    rate_hz: float
    sent: int
    estimates: int
    estimates_per_s: float
    latency_p50_ms: float
    latency_p99_ms: float
    late: int
    stale: int
    gaps: int
    rss_mib_early: float
    """The process's resident memory a tenth of the way into the run [MiB]."""
    rss_mib_end: float
    """The same at the end [MiB]."""
    churn_builds: int = 0
    """Opens of the churning peer that built a population meanwhile."""
    churn_refused: int = 0
    """Its opens the service refused (its per-peer build cap)."""


def _rss_mib() -> float:
    """Resident memory of this process [MiB] (Linux /proc; NaN elsewhere). Written by hand: one
    line of /proc is all it takes, psutil would be a dependency for it."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return float("nan")
    return pages * resource.getpagesize() / 2**20


def bench_load(
    sessions: int = 4,
    worlds: int = 40,
    rate: float = 30.0,
    seconds: float = 10.0,
    device: str = "auto",
    file: Path | None = None,
    connect: tuple[str, ...] = (),
    churn: bool = False,
) -> list[LoadResult]:
    """Run ``sessions`` robots at ``rate`` [Hz] for ``seconds`` against one embedded service whose
    population holds them all (groups = sessions), or against the running service at ``connect``
    (its own settings; the memory figures are then this process's, the robots', not the service's);
    with ``churn``, beside a peer that opens and closes sessions with new settings all the while."""
    if sessions < 1 or worlds < 1 or rate <= 0 or seconds <= 0:
        got = f"{sessions}, {worlds}, {rate}, {seconds}"
        raise ValueError(f"expected sessions, worlds, rate and seconds > 0, got {got}")
    traj = Trajectory.load(file or DATA_DIR / "smoke-foam_brick_pick_place_0.traj")
    if connect:
        endpoints, service = list(connect), contextlib.nullcontext()
    else:
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            endpoints = [f"tcp/127.0.0.1:{sock.getsockname()[1]}"]
        # The load is the benchmark's to choose, not the frame budget's: it measures what robots see.
        config = ServiceConfig(
            listen=tuple(endpoints), device=device, groups=sessions, max_sessions=max(64, sessions), rate_hz=0
        )
        service = TrackerNode(config)
    with service:
        clients = [TrackerClient(connect=endpoints, peer=f"robot-{i}") for i in range(sessions)]
        churner = _Churn(TrackerClient(connect=endpoints, peer="churn"), traj, worlds) if churn else None
        try:
            for c in clients:
                c.open_session(traj.robot, traj.object, traj.truth.initial_pose, q0=traj.truth.initial_q, worlds=worlds)
            received = [[] for _ in clients]
            for c, got in zip(clients, received, strict=True):
                c.on_pose(lambda est, got=got: got.append(est.latency_ms))
            with churner or contextlib.nullcontext():
                sent, (rss_early, rss_end) = _stream(clients, traj, rate, seconds)
            time.sleep(1.0)  # the last estimates in flight
            out = []
            for i, (c, got) in enumerate(zip(clients, received, strict=True)):
                status = c.status()
                lat = np.asarray(got) if got else np.full(1, np.nan)
                out.append(
                    LoadResult(
                        session=i,
                        worlds=worlds,
                        rate_hz=rate,
                        sent=sent[i],
                        estimates=len(got),
                        estimates_per_s=len(got) / seconds,
                        latency_p50_ms=float(np.percentile(lat, 50)),
                        latency_p99_ms=float(np.percentile(lat, 99)),
                        late=status.late,
                        stale=status.stale,
                        gaps=status.gaps,
                        rss_mib_early=rss_early,
                        rss_mib_end=rss_end,
                        churn_builds=churner.builds if churner else 0,
                        churn_refused=churner.refused if churner else 0,
                    )
                )
            return out
        finally:
            for c in clients + ([churner.client] if churner else []):
                c.close()


class _Churn:
    """A peer that opens a session with a new ``seed`` override (settings no population has: a
    build each) and closes it again, over and over, on a thread of its own while it is entered."""

    def __init__(self, client: TrackerClient, traj: Trajectory, worlds: int):
        self.client, self.traj, self.worlds = client, traj, worlds
        self.builds = self.refused = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> _Churn:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        t = self.traj
        while not self._stop.is_set():
            try:
                self.client.open_session(t.robot, t.object, t.truth.initial_pose, q0=t.truth.initial_q,
                                         worlds=self.worlds, overrides={"seed": self.builds + 1000})  # fmt: skip
                self.builds += 1
                self.client.close_session()
            except TrackerError:
                self.refused += 1
                self._stop.wait(0.5)  # as a client that backs off on a refusal


def _stream(
    clients: list[TrackerClient], traj: Trajectory, rate: float, seconds: float
) -> tuple[list[int], tuple[float, float]]:
    """Every client a robot on a thread of its own, replaying ``traj`` forth and back (no jump at
    the end) at ``rate`` [Hz] for ``seconds``; the frames each sent, and this process's resident
    memory early in the run and at its end [MiB]."""
    sent = [0] * len(clients)
    start = threading.Barrier(len(clients))

    def robot(i: int) -> None:
        c, period = clients[i], 2 * traj.frames - 2
        start.wait()
        t0 = time.perf_counter()
        n = 0
        while (now := time.perf_counter()) - t0 < seconds:
            time.sleep(max(0.0, t0 + n / rate - now))
            k = n % period
            row = k if k < traj.frames else period - k
            c.send(traj.frame(row, c.info.session, seq=n).model_copy(update={"stamp": n / rate}))
            n += 1
        sent[i] = n

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(len(clients))]
    for t in threads:
        t.start()
    threads[0].join(timeout=0.1 * seconds)
    rss_early = _rss_mib()
    for t in threads:
        t.join()
    return sent, (rss_early, _rss_mib())


def format_table(results: list[LoadResult]) -> str:
    head = "session  worlds  rate Hz  sent  estimates/s  latency p50 ms  p99 ms  late  stale  gaps"
    rows = [
        f"{r.session:>7}  {r.worlds:>6}  {r.rate_hz:>7g}  {r.sent:>4}  {r.estimates_per_s:>11.1f}"
        f"  {r.latency_p50_ms:>14.1f}  {r.latency_p99_ms:>6.1f}  {r.late:>4}  {r.stale:>5}  {r.gaps:>4}"
        for r in results
    ]
    r = results[0]
    growth = 100 * (r.rss_mib_end / r.rss_mib_early - 1)
    memory = (
        f"resident memory: {r.rss_mib_early:.1f} MiB a tenth of the way in,"
        f" {r.rss_mib_end:.1f} at the end ({growth:+.2f} %)"
    )
    churn = [f"churn: another peer built {r.churn_builds} populations meanwhile, {r.churn_refused} opens refused"]
    return "\n".join([head, *rows, memory, *(churn if r.churn_builds or r.churn_refused else [])])


def as_dicts(results: list[LoadResult]) -> list[dict]:
    return [asdict(r) for r in results]
