"""Torch ops and Warp kernels of one tracker stage as one replayable graph.

On CUDA, a torch CUDA graph records the stage on Warp's stream, with Warp joining the capture as
an external one: the population's kernels (MuJoCo-Warp's solver loop as a conditional node), the
forward kinematics and every torch op of the cost, window and estimate become one graph, replayed
with one launch. Torch's temporaries live in the graph's private pool, so a replay allocates
nothing. On the CPU the stage runs as plain calls (torch has no CPU graphs); its physics is still
one Warp CPU graph replay.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
import warp as wp

from inhand_tracker.sim_backend import no_collection

__all__ = ["CapturedOps"]


class CapturedOps:
    """``fn`` (no arguments, no return: it reads and writes fixed tensors) as one graph replay.

    The first call on CUDA runs ``fn`` eagerly, which compiles kernels and initialises torch's
    lazy state, and then records it; later calls replay the record. ``generators``: the torch
    generators ``fn`` draws from, registered so that each replay draws fresh numbers. ``pool``:
    another CapturedOps whose memory pool to share (stages that never run at once).
    """

    def __init__(
        self,
        fn: Callable[[], None],
        device: wp.context.Device,
        generators: Sequence[torch.Generator] = (),
        pool: CapturedOps | None = None,
    ):
        self.fn = fn
        self.device = device
        self.generators = tuple(generators)
        self._pool_from = pool
        self.graph: torch.cuda.CUDAGraph | None = None
        self._warp_graph = None  # keeps Warp's arrays allocated during the capture alive
        self.stream = wp.stream_to_torch(device.stream) if device.is_cuda else None
        can_capture = not self.generators or hasattr(torch.cuda.CUDAGraph, "register_generator_state")
        self.enabled = device.is_cuda and can_capture

    @property
    def captured(self) -> bool:
        return self.graph is not None

    def invalidate(self) -> None:
        """Record again at the next call (``fn`` now launches different work)."""
        self.graph = self._warp_graph = None

    def __call__(self) -> None:
        with wp.ScopedDevice(self.device):
            if self.graph is not None:
                with torch.cuda.stream(self.stream):
                    self.graph.replay()
                return
            if self.stream is None:
                self.fn()
                return
            with torch.cuda.stream(self.stream):
                self.fn()
            if self.enabled:
                self._capture()

    def _capture(self) -> None:
        graph = torch.cuda.CUDAGraph()
        for generator in self.generators:
            graph.register_generator_state(generator)
        pool = self._pool_from.graph.pool() if self._pool_from is not None and self._pool_from.graph else None
        # thread_local: the service's Zenoh threads keep running while the loop thread captures.
        with (
            no_collection(),
            torch.cuda.graph(graph, pool=pool, stream=self.stream, capture_error_mode="thread_local"),
            wp.ScopedCapture(device=self.device, stream=self.device.stream, external=True) as capture,
        ):
            self.fn()
        self.graph, self._warp_graph = graph, capture.graph
