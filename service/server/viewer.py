"""The operator's view, live in a browser (setting ``view_port``): Newton's own viewer
(``ViewerViser``) shows one session's worlds as its population holds them, every world's hand and
object overlaid and see-through, each world's object faded by its share of the estimate; in them,
the real robot's fingertips (red, by forward kinematics of the joints it sent), the estimate's pose
as a frame and the cost-weighted mean's 95 % position region as a sphere with its radius written
beside it. The panel picks the session and shows its state, frame, rate, latency, cost, mass and
friction, and what the colours mean.

The drawing and the web server run in a process of their own (:mod:`.view_drawing`): in this one
their Python (Newton's ``log_state``, viser's sending) would take the interpreter's lock from the
tracking loop, and a watched session's frames would run late. At most ``rate_hz`` times a second,
only while a browser is connected and the last snapshot has been drawn, the loop queues copies of
the shown worlds' body poses, weights and the real fingertips behind the frame, and on a later turn,
once they are on the host, puts them in memory shared with the drawing process and tells it so.
With nobody watching the view costs a look at a pipe ten times a second."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import multiprocessing
import time
import weakref
from multiprocessing import shared_memory

import numpy as np
import torch

from inhand_tracker.protocol import Estimate

from .outputs import Output
from .view_drawing import draw_forever
from .view_messages import Close, Draw, Drawn, EstimateView, Failed, Panel, Ready, Show, Warm, layout

__all__ = ["LiveView"]

log = logging.getLogger(__name__)

_START_S = 120.0
"""How long the drawing process may take to import its libraries and open its port [s]."""


@dataclasses.dataclass
class _Snapshot:
    """One drawing's copies into the host buffer, queued on the device behind the frame they show."""

    message: Draw
    """What goes to the drawing process with it."""
    taken: torch.cuda.Event | None
    """Recorded behind the copies on CUDA: the snapshot is shipped once it has passed."""


class LiveView(Output):
    """A browser view of the service's sessions, on ``host:port``."""

    name = "live view"

    def __init__(self, host: str, port: int, rate_hz: float = 10.0):
        context = multiprocessing.get_context("spawn")  # a fork would copy the loop's threads and CUDA context
        self._pipe, child = context.Pipe()
        self._process = context.Process(target=draw_forever, args=(child, host, port), name="live-view", daemon=True)
        self._process.start()
        child.close()
        if not self._pipe.poll(_START_S):
            self.close()
            raise RuntimeError(f"the live view did not start within {_START_S:.0f} s")
        answer = self._pipe.recv()
        if not isinstance(answer, Ready):
            self.close()
            raise RuntimeError(f"the live view on {host}:{port} failed: {answer.reason}")
        self.period = 1.0 / rate_hz
        self._last = 0.0
        self._busy = False
        self._choice, self._clients = "none", 0
        self._shown: tuple | None = None
        self._drawn = -1
        """The shown session's frame count at the last drawing."""
        self._shared: shared_memory.SharedMemory | None = None
        self._places: dict[str, tuple[int, int]] = {}
        self._staged: torch.Tensor | None = None
        self._snapshot: _Snapshot | None = None
        self._turn = contextlib.nullcontext()
        log.info("live view on http://%s:%d", host, answer.port)

    def warm(self, manager) -> None:
        """The drawing process draws one world of the service's first robot and object, so that
        its kernels are compiled before the first browser connects."""
        from inhand_tracker.sim_backend import PopulationConfig

        robot, obj = next(iter(manager.robots.values())), next(iter(manager.objects.values()))
        self._send(Warm(robot, obj, PopulationConfig()))
        if manager.device.is_cuda:
            # The copies are device work: a build on another thread captures graphs, which another
            # thread's launches would break. On a CPU each thread's work runs apart.
            self._turn = manager.turn

    def _send(self, message: Warm | Show | Panel | Draw) -> None:
        self._pipe.send(message)
        self._busy = True

    def _receive(self) -> None:
        """What the drawing process said since the last turn."""
        while self._pipe.poll():
            said: Drawn | Failed = self._pipe.recv()
            if isinstance(said, Failed):
                raise RuntimeError(f"the live view's drawing failed: {said.reason}")  # the outputs close it
            self._choice, self._clients = said.choice, said.clients
            self._busy = self._busy and not said.done

    def tick(self, sessions: dict) -> None:
        """Hand the chosen session's worlds and latest estimate to the drawing process
        (``sessions``: the manager's, by id)."""
        snap = self._snapshot
        if snap is not None and (snap.taken is None or snap.taken.query()):
            self._ship(snap)  # the drawing process is idle: it had answered when the snapshot was taken
        now = time.monotonic()
        if now - self._last < self.period:
            return
        self._last = now
        self._receive()
        ids = tuple(sorted(sessions)) or ("none",)
        session = sessions.get(self._choice) or (sessions[ids[0]] if sessions else None)
        if not self._clients or self._busy or self._snapshot is not None:
            return
        if session is None:
            if self._shown is not None:
                self._shown = None
                self._send(Panel("No session is tracking.", ids))
            return
        key = (session.id, session.group, weakref.ref(session.pool.tracker.pop))  # no hold on a closed one's
        if self._shown != key:
            self._show(session, key)
        elif session.frames == self._drawn:  # nothing moved: the panel alone, the browser redraws nothing
            self._send(Panel(self._describe(session), ids))
        else:
            self._drawn = session.frames
            self._snapshot = self._take(session, ids)

    def _show(self, session, key: tuple) -> None:
        """A new session or group: the drawing process builds its replica of the K worlds."""
        pop = session.pool.tracker.pop
        self._shown, self._drawn = key, -1
        self._places = layout(pop.K, pop.bodies, pop.L)
        size = max(stop for _, stop in self._places.values())
        if self._shared is not None:
            self._shared.close()
            self._shared.unlink()
        self._shared = shared_memory.SharedMemory(create=True, size=size * 4)
        pinned = pop.device.is_cuda
        self._staged = torch.empty(size, dtype=torch.float32, pin_memory=pinned)
        self._send(Show(pop.robot_spec, pop.object, pop.config, pop.K, self._shared.name, pop.L))

    def _take(self, session, ids: tuple[str, ...]) -> _Snapshot:
        """Queue the shown worlds' copies behind the frame (no wait on the device)."""
        pool, group = session.pool, session.group
        pop, staged, at = pool.tracker.pop, self._staged, self._places
        with self._turn, pop.on_stream():
            parts = {
                "body_q": pop.state_views["body_q"](pop.state_0)[group],
                "weights": pool.tracker.weights()[group],
                "tips": pool.tracker.fk.pos[group],
            }
            for name, value in parts.items():
                a, b = at[name]
                staged[a:b].view_as(value).copy_(value, non_blocking=True)
            taken = None
            if pop.device.is_cuda:
                taken = torch.cuda.Event()
                taken.record()
        estimate = session.latest
        shown = None if estimate is None else EstimateView(
            np.asarray(estimate.pose), np.asarray(estimate.mean_pose[:3]),
            np.asarray(estimate.covariance, np.float32)[:3, :3],
        )  # fmt: skip
        return _Snapshot(Draw(shown, self._describe(session), ids), taken)

    def _ship(self, snap: _Snapshot) -> None:
        """The snapshot is on the host: into the shared memory, and the drawing process told."""
        np.ndarray(self._staged.shape, np.float32, buffer=self._shared.buf)[:] = self._staged.numpy()
        self._send(snap.message)
        self._snapshot = None

    def _describe(self, session) -> str:
        """The panel's text for ``session``: its state and the figures an operator watches."""
        estimate: Estimate | None = session.latest
        rate = self._rate(session)
        if estimate is None:
            return f"**{session.name or session.id}**: waiting for its first frame"
        latency = np.percentile(np.asarray(session.latencies), 50) if session.latencies else 0.0
        notice = f"\n\n{session.last_error}" if session.last_error else ""
        return (
            f"**{session.name or session.id}** ({session.robot}, {session.object}, {session.method},"
            f" K={session.pool.tracker.K}): **{estimate.status}**\n\n"
            f"| frame | rate | latency p50 | cost | mass | friction |\n|---|---|---|---|---|---|\n"
            f"| {estimate.seq} | {rate:.1f} Hz | {latency:.1f} ms | {estimate.cost:.2f} | {estimate.mass * 1e3:.0f} g"
            f" | {estimate.friction:.2f} |{notice}"
        )

    @staticmethod
    def _rate(session) -> float:
        """The robot's frames per second by its own clock over its last 30 frames: what it sends,
        whatever the service's or the browser's pace."""
        s = session.stamps
        return (len(s) - 1) / (s[-1] - s[0]) if len(s) > 1 and s[-1] > s[0] else 0.0

    def close(self) -> None:
        try:
            self._pipe.send(Close())
        except OSError:
            pass  # it has gone already
        self._process.join(timeout=10)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(timeout=5)
        self._pipe.close()
        if getattr(self, "_shared", None) is not None:
            self._shared.close()
            self._shared.unlink()
