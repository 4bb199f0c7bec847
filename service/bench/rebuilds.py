"""Populations built and dropped in a loop: whether the service's memory comes back. Each cycle
opens a session with settings no population has (a new seed), so the service builds a population
for it, and closes it, so the population is dropped: what a peer opening with new settings each
time, or a lab restarting its robot's session all day, costs. The process's resident memory and
the device's (Warp's pool and torch's allocator) are read after the first tenth of the cycles and
at the end."""

from __future__ import annotations

import gc
import time
from dataclasses import asdict, dataclass

from inhand_tracker.protocol import OpenSession, Trajectory
from inhand_tracker.service.paths import CONFIG_DIR, DATA_DIR
from inhand_tracker.service.server import ServiceConfig, SessionManager
from inhand_tracker.service.server.budget import device_name
from inhand_tracker.sim_backend import load_catalog, load_robot

from .load import _rss_mib
from .progress import progress_bar
from .sim import used_bytes

__all__ = ["RebuildResult", "bench_rebuilds", "format_table"]


@dataclass
class RebuildResult:
    cycles: int
    worlds: int
    device: str
    build_s_mean: float
    """Mean time of one open that builds a population plus its close [s]."""
    rss_mib_warm: float
    """The process's resident memory after the first tenth of the cycles [MiB]."""
    rss_mib_end: float
    """The same after the last cycle [MiB]."""
    device_mib_warm: float
    """Device memory held by Warp's pool and torch's allocator then [MiB] (0 on a CPU)."""
    device_mib_end: float

    @property
    def rss_growth_percent(self) -> float:
        return 100 * (self.rss_mib_end / self.rss_mib_warm - 1)


def _device_mib(device) -> float:
    return used_bytes(device) / 2**20 if device.is_cuda else 0.0  # on a CPU used_bytes is the RSS


def bench_rebuilds(cycles: int = 1000, worlds: int = 8, device: str = "auto") -> RebuildResult:
    """Open and close ``cycles`` sessions, each building and dropping a population of ``worlds``
    worlds with the bundled robot and object; a population held by another session stays all along
    (the service is never empty, as in use)."""
    if cycles < 10 or worlds < 1:
        raise ValueError(f"expected cycles >= 10 and worlds >= 1, got {cycles}, {worlds}")
    traj = Trajectory.load(DATA_DIR / "smoke-foam_brick_pick_place_0.traj")
    robot = load_robot(CONFIG_DIR / "robots/allegro.toml")
    config = ServiceConfig(
        device=device, groups=1, rate_hz=0, max_opens_per_minute=10**6, max_builds_per_minute_per_peer=10**6
    )
    manager = SessionManager(config, {robot.name: robot}, load_catalog())

    def request(seed: int) -> OpenSession:
        return OpenSession(
            robot=traj.robot, object=traj.object, p0=traj.truth.initial_pose, worlds=worlds, overrides={"seed": seed}
        )

    manager.open(request(0))
    warm_at, start = max(1, cycles // 10), time.perf_counter()
    rss_warm = device_warm = 0.0
    with progress_bar(cycles, "builds and drops", "cycle") as bar:
        for cycle in range(1, cycles + 1):
            info = manager.open(request(cycle))
            manager.close(info.session, info.token)
            bar.update()
            if cycle == warm_at:
                gc.collect()
                rss_warm, device_warm = _rss_mib(), _device_mib(manager.device)
    gc.collect()
    return RebuildResult(
        cycles, worlds, device_name(manager.device), (time.perf_counter() - start) / cycles,
        rss_warm, _rss_mib(), device_warm, _device_mib(manager.device),
    )  # fmt: skip


def format_table(r: RebuildResult) -> str:
    return "\n".join(
        [
            f"{r.cycles} populations of {r.worlds} worlds built and dropped on {r.device}, {r.build_s_mean:.2f} s each",
            f"resident memory: {r.rss_mib_warm:.1f} MiB after {max(1, r.cycles // 10)} cycles, {r.rss_mib_end:.1f}"
            f" MiB after {r.cycles} ({r.rss_growth_percent:+.2f} %)",
            f"device memory: {r.device_mib_warm:.1f} MiB, then {r.device_mib_end:.1f} MiB",
        ]
    )


def as_dict(r: RebuildResult) -> dict:
    return asdict(r) | {"rss_growth_percent": r.rss_growth_percent}
