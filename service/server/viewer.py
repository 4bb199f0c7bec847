"""The tracking, live in a browser (setting ``view_port``): Newton's own viewer (``ViewerViser``)
shows one session's worlds as its population holds them, every world's hand and object overlaid,
each world's object faded by its share of the estimate; on top, the real robot's fingertips (red,
by forward kinematics of the joints it sent), the estimate's pose as a frame and the cost-weighted
mean's 95 % position region as a sphere. A session is chosen in the page.

It draws on the service's loop thread, at most ``rate_hz`` times a second and only while a browser
is connected: with nobody watching it costs a few dictionary look-ups ten times a second."""

from __future__ import annotations

import logging
import time

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


class LiveView(Output):
    """A browser view of the service's sessions, on ``host:port``."""

    name = "live view"

    def __init__(self, host: str, port: int, rate_hz: float = 10.0):
        from newton.viewer import ViewerViser

        self.viewer = ViewerViser(host=host, port=port, verbose=False, label="inhand-tracker")
        self.server = self.viewer.server
        self.period = 1.0 / rate_hz
        self._last = 0.0
        self._model = None
        self._shown: tuple | None = None
        self._object_shapes: torch.Tensor | None = None
        self._choice = self.server.gui.add_dropdown("session", options=("none",), initial_value="none")
        self._estimate = self.server.scene.add_frame("/inhand/estimate", axes_length=0.04, axes_radius=0.002)
        self._look_at: np.ndarray | None = None
        self._aimed: set[int] = set()
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
        self._draw(pop, torch.ones(1, device=wp.device_to_torch(pop.model.device)))
        self._model = self._shown = None  # a session's population is shown anew

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
        pool, group = session.pool, session.group
        pop = pool.tracker.pop
        if pop.model is not self._model or self._shown != (session.id, group):
            self._show(pop, group)
            self._shown = (session.id, group)
        if clients.keys() - self._aimed:  # a new browser: after the viewer's own set-up, which places the camera
            self._aim()
            self._aimed = set(clients)
        self._draw(pop, pool.tracker.weights()[group])
        # The real robot as it stands: its fingertips by forward kinematics of the joints it sent.
        tips = pool.tracker.fk.pos[group].detach().cpu().numpy()
        self.server.scene.add_point_cloud(
            "/inhand/real_fingertips", points=tips, colors=(220, 20, 60), point_size=0.012, point_shape="circle"
        )
        estimate: Estimate | None = session.latest
        if estimate is not None:
            p = estimate.pose.astype(np.float64)
            self._estimate.position, self._estimate.wxyz = p[:3], (p[6], p[3], p[4], p[5])
            spread = float(np.sqrt(np.linalg.eigvalsh(np.asarray(estimate.covariance, np.float64)[:3, :3]).max()))
            self.server.scene.add_icosphere(  # the same name replaces the last one
                "/inhand/mean_95",
                radius=max(np.sqrt(_CHI2_3_95) * spread, 1e-4),
                color=(255, 140, 0),
                opacity=0.3,
                position=np.asarray(estimate.mean_pose[:3], np.float64),
            )

    def _draw(self, pop, weights: torch.Tensor) -> None:
        """The shown group's worlds as they stand, each object faded by its ``weights`` (K,)."""
        opacity = _FAINTEST + (1.0 - _FAINTEST) * weights / weights.max().clamp_min(1e-12)
        wp.to_torch(pop.model.shape_opacity)[self._object_shapes] = opacity[self._object_worlds].to(torch.float32)
        self.viewer.begin_frame(time.monotonic())
        self.viewer.log_state(pop.state_0)
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
        self._object_shapes = torch.as_tensor(shapes, device=device)
        self._object_worlds = torch.as_tensor(shape_world[shapes] - group * pop.K, device=device)

    def close(self) -> None:
        self.server.stop()
