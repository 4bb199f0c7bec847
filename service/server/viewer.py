"""The operator's view, live in a browser (setting ``view_port``): Newton's own viewer
(``ViewerViser``) shows one session's worlds as its population holds them, every world's hand and
object overlaid and see-through, each world's object faded by its share of the estimate; in them,
the real robot's fingertips (red, by forward kinematics of the joints it sent), the estimate's pose
as a frame and the cost-weighted mean's 95 % position region as a sphere with its radius written
beside it. The panel picks the session and shows its state, frame, rate, latency, cost, mass and
friction, and what the colours mean.

At most ``rate_hz`` times a second and only while a browser is connected, the service's loop takes
a snapshot of the shown worlds (a copy of their bodies' poses, the weights and the fingertips, on
the device) and a thread of the view's own draws it, skipping the snapshot while the last one is
still being drawn. The drawing still shares the process with the loop: its Python (Newton's
``log_state``, viser's sending) holds the interpreter's lock, and on CUDA its device work takes
turns with the loop's, so a watched session's frames run somewhat slower on a CPU. With nobody
watching the view costs a few dictionary look-ups ten times a second. Its kernels are compiled at
the service's warm-up, so a browser that connects later adds no compilation to a frame."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from inhand_tracker.protocol import Estimate

from .outputs import Output

__all__ = ["LiveView"]

log = logging.getLogger(__name__)

_CHI2_3_95 = 7.815
"""The 95 % quantile of a chi-square with 3 degrees of freedom: a 3-D Gaussian's 95 % region."""
_CAMERA_OFFSET = np.array([0.3, -0.3, 0.2])
"""Where the camera stands from the object [m]: looking at it at yaw 135 deg, pitch -25 deg."""
_FAINTEST = 0.08
"""The opacity of a world whose weight is nil: faded, still visible."""
_OBJECT_OPACITY = 0.6
"""The opacity of the heaviest world's object: the uncertainty region inside it shows through."""
_HAND_OPACITY = 0.35
"""The opacity of the hands' links: the real fingertips inside them show through."""
_LEGEND = """**Colours.** Red dots: the real fingertips, from the joints the robot sent. Orange sphere:
the 95 % region of the object's position. Axes: the estimate. Faded objects: the worlds, each as
opaque as its share of the estimate."""


@dataclass
class _Snapshot:
    """What one drawing shows, taken on the loop thread."""

    pop: object
    """The session's population (its model is what is drawn)."""
    key: tuple
    """(session id, group): a new one is shown anew."""
    state: object
    """A Newton State holding the population's bodies' poses when it was taken."""
    weights: torch.Tensor
    """The shown group's worlds' shares of the estimate, (K,)."""
    tips: torch.Tensor
    """The real fingertips by forward kinematics of the robot's joints, (L, 3) [m]."""
    estimate: Estimate | None
    text: str
    """The panel's text."""
    taken: object = None
    """A Warp event recorded behind the copies (CUDA), which the drawing waits for."""


class LiveView(Output):
    """A browser view of the service's sessions, on ``host:port``."""

    name = "live view"

    def __init__(self, host: str, port: int, rate_hz: float = 10.0):
        from newton.viewer import ViewerViser

        self.viewer = ViewerViser(host=host, port=port, verbose=False, label="inhand-tracker")
        self.server = self.viewer.server
        # Newton's viewer offers a simulator's controls (pause, step, "Show Cloth", ...); none means
        # anything to an operator of a tracker, so the panel holds the tracker's alone. Its option
        # handles go too: the viewer syncs whatever it still holds there on every frame.
        self.server.gui.reset()
        self.viewer._viewer_option_handles.clear()
        self.viewer._simulation_gui_handles.clear()
        self.period = 1.0 / rate_hz
        self._last = 0.0
        self._model = None
        self._shown: tuple | None = None
        self._object_shapes: torch.Tensor | None = None
        self._counted: tuple[str, int, float] | None = None
        self._choice = self.server.gui.add_dropdown("session", options=("none",), initial_value="none")
        self._panel = self.server.gui.add_markdown("No session is tracking.")
        self.server.gui.add_markdown(_LEGEND)
        self._estimate = self.server.scene.add_frame("/inhand/estimate", axes_length=0.04, axes_radius=0.002)
        self._look_at: np.ndarray | None = None
        self._aimed: set[int] = set()
        self._turn = contextlib.nullcontext()
        self._state = None
        self._pending: _Snapshot | None = None
        self._drawing = threading.Lock()
        self._wake = threading.Event()
        self._closing = False
        self._failed: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()
        log.info("live view on http://%s:%d", host, port)

    def _aim(self) -> None:
        """Point the browsers' cameras at the object, from the front above (Newton's camera: z up,
        yaw and pitch in degrees)."""
        target = self._look_at if self._look_at is not None else np.zeros(3)
        self.viewer.set_camera(wp.vec3(*(target + _CAMERA_OFFSET)), pitch=-25.0, yaw=135.0)

    def warm(self, manager) -> None:
        """Draw a one-world population of the service's first robot and object once, so that the
        kernels the view runs are compiled at the service's warm-up, not on its tracking loop when
        the first browser connects."""
        from inhand_tracker.sim_backend import Population, PopulationConfig

        robot, obj = next(iter(manager.robots.values())), next(iter(manager.objects.values()))
        pop = Population(robot, obj, PopulationConfig(groups=1, worlds=1, device=str(manager.device)))
        self._show(pop, 0)
        self._draw(pop, pop.state_0, torch.ones(1, device=wp.device_to_torch(pop.model.device)))
        self._model = self._shown = None  # a session's population is shown anew
        if wp.get_device(str(manager.device)).is_cuda:
            # A CUDA device's work is taken in turns with the builds, whose graph captures another
            # thread's launches would break; on a CPU each thread's kernels run apart.
            self._turn = manager.turn

    def tick(self, sessions: dict) -> None:
        """Draw the chosen session's worlds and latest estimate (``sessions``: the manager's, by id)."""
        now = time.monotonic()
        if now - self._last < self.period:
            return
        self._last = now
        ids = tuple(sorted(sessions))
        session = sessions.get(self._choice.value) or (sessions[ids[0]] if ids else None)
        if session is not None and session.latest is not None:
            self._look_at = session.latest.pose[:3].astype(np.float64)  # where a new browser looks
        clients = self.server.get_clients()
        if session is None or not clients:
            return
        if tuple(self._choice.options) != ids:
            self._choice.options = ids
        if self._failed is not None:
            raise RuntimeError("the live view's drawing failed") from self._failed  # the outputs close it
        if self._drawing.locked():
            return  # the last snapshot is still being drawn: this one is skipped, the loop goes on
        self._pending = self._snapshot(session)
        self._wake.set()

    def _snapshot(self, session) -> _Snapshot:
        """The shown worlds as they stand: copies on the device, queued behind the frame."""
        pool, group = session.pool, session.group
        pop = pool.tracker.pop
        with self._turn, pop.on_stream():
            if self._state is None or self._state.body_q.shape != pop.state_0.body_q.shape:
                self._state = pop.model.state()  # once per population shown, not per drawing
            wp.copy(self._state.body_q, pop.state_0.body_q)
            weights = pool.tracker.weights()[group].clone()
            tips = pool.tracker.fk.pos[group].detach().clone()
            taken = wp.record_event() if pop.model.device.is_cuda else None
        return _Snapshot(
            pop, (session.id, group), self._state, weights, tips, session.latest, self._describe(session), taken
        )

    def _run(self) -> None:
        """The view's thread: draws each snapshot the loop hands it."""
        while True:
            self._wake.wait()
            self._wake.clear()
            if self._closing:
                return
            with self._drawing:
                snapshot, self._pending = self._pending, None
                if snapshot is None:
                    continue
                try:
                    self._show_snapshot(snapshot)
                except Exception as exc:
                    log.exception("the live view failed to draw")
                    self._failed = exc
                    return

    def _show_snapshot(self, snap: _Snapshot) -> None:
        """Draw one snapshot: the worlds, the real fingertips, the estimate and the panel."""
        with self._turn:
            if snap.taken is not None:
                wp.synchronize_event(snap.taken)
            if snap.pop.model is not self._model or self._shown != snap.key:
                self._show(snap.pop, snap.key[1])
                self._shown = snap.key
            clients = self.server.get_clients()
            if clients.keys() - self._aimed:  # a new browser: after the viewer's own set-up, which places the camera
                self._aim()
                self._aimed = set(clients)
            self._draw(snap.pop, snap.state, snap.weights)
            tips = snap.tips.cpu().numpy()
        self.server.scene.add_point_cloud(
            "/inhand/real_fingertips", points=tips, colors=(220, 20, 60), point_size=0.012, point_shape="circle"
        )
        self._panel.content = snap.text
        estimate = snap.estimate
        if estimate is not None:
            p = estimate.pose.astype(np.float64)
            self._estimate.position, self._estimate.wxyz = p[:3], (p[6], p[3], p[4], p[5])
            radius = np.sqrt(_CHI2_3_95 * np.linalg.eigvalsh(np.asarray(estimate.covariance, np.float64)[:3, :3]).max())
            centre = np.asarray(estimate.mean_pose[:3], np.float64)
            self.server.scene.add_icosphere(  # the same name replaces the last one
                "/inhand/mean_95", radius=max(radius, 1e-4), color=(255, 140, 0), opacity=0.45, position=centre
            )
            # A label draws over everything: the region's size reads even where the sphere is small.
            above = centre + np.array([0.0, 0.0, radius + 0.01])
            self.server.scene.add_label("/inhand/mean_95_label", f"95 %: {radius * 1e3:.1f} mm", position=above)

    def _describe(self, session) -> str:
        """The panel's text for ``session``: its state and the figures an operator watches."""
        estimate: Estimate | None = session.latest
        now = time.monotonic()
        last = self._counted
        rate = (session.frames - last[1]) / (now - last[2]) if last and last[0] == session.id and now > last[2] else 0.0
        self._counted = (session.id, session.frames, now)
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

    def _draw(self, pop, state, weights: torch.Tensor) -> None:
        """The shown group's worlds in ``state``, each object faded by its ``weights`` (K,)."""
        opacity = _FAINTEST + (_OBJECT_OPACITY - _FAINTEST) * weights / weights.max().clamp_min(1e-12)
        wp.to_torch(pop.model.shape_opacity)[self._object_shapes] = opacity[self._object_worlds].to(torch.float32)
        self.viewer.begin_frame(time.monotonic())
        self.viewer.log_state(state)
        self.viewer.end_frame()

    def _show(self, pop, group: int) -> None:
        """A new population or session: its model, its group's worlds overlaid in place."""
        self.viewer.set_model(pop.model)
        self.viewer.show_collision = True  # the population's shapes are collision shapes, what the physics sees
        self._model = pop.model
        worlds = range(group * pop.K, (group + 1) * pop.K)
        self.viewer.set_visible_worlds(list(worlds))
        self.viewer.set_world_offsets((0.0, 0.0, 0.0))
        shape_body = pop.model.shape_body.numpy()
        shape_world = pop.model.shape_world.numpy()
        nb = pop.model.body_count // pop.W
        mine = (shape_body >= 0) & (shape_body % nb == pop.built.object_body) & np.isin(shape_world, list(worlds))
        shapes = np.flatnonzero(mine)
        device = wp.device_to_torch(pop.model.device)
        hand = torch.as_tensor(np.flatnonzero((shape_body >= 0) & ~mine), device=device)
        wp.to_torch(pop.model.shape_opacity)[hand] = _HAND_OPACITY
        self._object_shapes = torch.as_tensor(shapes, device=device)
        self._object_worlds = torch.as_tensor(shape_world[shapes] - group * pop.K, device=device)

    def close(self) -> None:
        self._closing = True
        self._wake.set()
        self._thread.join(timeout=10)
        self.server.stop()
