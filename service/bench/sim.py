"""`inhand-tracker bench sim`: milliseconds per control frame and memory per world."""

from __future__ import annotations

import gc
import os
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
import warp as wp

from inhand_tracker.sim_backend import Population, PopulationConfig, resolve_device
from inhand_tracker.sim_backend.grasp import plan_pinch
from inhand_tracker.sim_backend.kinematics import Kinematics
from inhand_tracker.sim_backend.objects import catalog_object
from inhand_tracker.sim_backend.robots import HandSpec

__all__ = ["SimBenchResult", "bench_sim", "release_memory", "used_bytes"]


@dataclass(frozen=True)
class SimBenchResult:
    worlds: int
    substeps: int
    solver: str
    device: str
    median_ms: float
    p95_ms: float
    bytes_per_world: float
    build_s: float


def used_bytes(device: wp.context.Device) -> int:
    if device.is_cuda:
        # Warp's memory pool keeps freed blocks, so the driver's free memory says little; the
        # pool's own count of live bytes, plus torch's, is what a population holds.
        warp_bytes = wp.get_mempool_used_mem_current(device) if wp.is_mempool_enabled(device) else 0
        return int(warp_bytes + torch.cuda.memory_allocated(wp.device_to_torch(device)))
    with open("/proc/self/statm") as f:  # resident set size, pages
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def bench_sim(
    worlds: list[int],
    *,
    substeps: int = PopulationConfig.substeps,
    frames: int = 60,
    warmup: int = 10,
    obj: str = "foam_brick",
    device: str = "auto",
    solver: str = "auto",
) -> list[SimBenchResult]:
    """Time graph replays of a held grasp (every world squeezing the object) for each K in ``worlds``."""
    dev = resolve_device(device)
    spec = HandSpec()
    grasp = plan_pinch(Kinematics(spec), catalog_object(obj))

    # A throwaway population takes the one-time costs (kernel compiles, CUDA context and module
    # loads) out of the first K's build time and memory.
    def config(k: int) -> PopulationConfig:
        return PopulationConfig(worlds=k, substeps=substeps, device=dev.alias, solver=solver)

    Population(spec, catalog_object(obj), config(1)).step()
    results = []
    for k in worlds:
        wp.synchronize_device(dev)
        before = used_bytes(dev)
        t0 = time.perf_counter()
        pop = Population(spec, catalog_object(obj), config(k))
        pop.reset_state(grasp.object_pose, grasp.q_touch)
        pop.set_targets(grasp.q_squeeze[None])
        for _ in range(warmup):
            pop.step()
        wp.synchronize_device(dev)
        build_s = time.perf_counter() - t0
        used = used_bytes(dev) - before
        times = np.empty(frames)
        for i in range(frames):
            t = time.perf_counter()
            pop.step()
            wp.synchronize_device(dev)
            times[i] = (time.perf_counter() - t) * 1e3
        lost = int((pop.obs.health != 0).sum())
        if lost:
            print(f"  note: {lost} of {k} worlds lost the object during the benchmark")
        results.append(
            SimBenchResult(
                worlds=k,
                substeps=substeps,
                solver=pop.config.solver_settings.name,
                device=dev.alias,
                median_ms=float(np.median(times)),
                p95_ms=float(np.percentile(times, 95)),
                bytes_per_world=used / k,
                build_s=build_s,
            )
        )
        del pop
        release_memory(dev)
    return results


def release_memory(device: wp.context.Device) -> None:
    """Free what a dropped population held before the next one is measured: solvers and graphs
    hold reference cycles, and torch keeps freed blocks cached."""
    gc.collect()
    if device.is_cuda:
        torch.cuda.empty_cache()


def format_table(results: list[SimBenchResult]) -> str:
    lines = [
        "| device | K | substeps | solver | median ms/frame | p95 ms/frame | memory/world | build s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r.device} | {r.worlds} | {r.substeps} | {r.solver} | {r.median_ms:.2f} | {r.p95_ms:.2f} | "
            f"{r.bytes_per_world / 1024:.0f} KiB | {r.build_s:.1f} |"
        )
    return "\n".join(lines)


def as_dicts(results: list[SimBenchResult]) -> list[dict]:
    return [asdict(r) for r in results]
