"""The live view's drawing process: Newton's own viewer (``ViewerViser``) and its web server, in a
process of their own so that nothing a browser does takes the tracking loop's interpreter lock.

The service (:mod:`.viewer`) sends it, over a pipe, what to show (a session's robot, object and K)
and then, a few times a second, where the shown worlds' bodies are: their poses, weights and the
real fingertips through shared memory, the panel's text and the estimate with the message. It
draws them on a replica of the session's model, one group of K worlds built on the CPU (the worlds
differ in pose, mass and friction, never in shape), and answers each message when done, so the
service hands it nothing while it draws. It tells the service which session the browser picked and
how many browsers are connected. It ends when the service closes the pipe or dies."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time
from multiprocessing import shared_memory
from multiprocessing.connection import Connection

import numpy as np
import warp as wp

from .view_messages import Close, Draw, Drawn, EstimateView, Failed, Panel, Ready, Show, Warm, layout

__all__ = ["Drawing", "draw_forever"]

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
the 95 % region of the object's position around the estimate. Axes: the estimate. Blue objects:
the worlds, each as opaque as its share of the estimate. The hand's links keep one colour each."""
_LINK_PALETTE = np.array(
    [(0.62, 0.62, 0.66), (0.80, 0.60, 0.45), (0.45, 0.65, 0.50), (0.55, 0.55, 0.80), (0.80, 0.75, 0.45),
     (0.65, 0.50, 0.70), (0.45, 0.70, 0.75), (0.75, 0.50, 0.50)], np.float32,
)  # fmt: skip
"""The hand's link colours, by the link's index in the robot: the same link the same colour in
every world and every session, and neighbouring links apart (Newton's default palette runs by
shape, so one link takes a different colour in each world)."""
_OBJECT_COLOUR = (0.25, 0.45, 0.85)
_POLL_S = 0.1
"""How often an idle drawing process looks for new browsers and the picked session [s]."""


class Drawing:
    """Newton's viewer with the tracker's panel, drawing one group of K worlds at a time."""

    def __init__(self, host: str, port: int):
        from newton.viewer import ViewerViser

        self.viewer = ViewerViser(host=host, port=port, verbose=False, label="inhand-tracker")
        self.server = self.viewer.server
        # Newton's viewer offers a simulator's controls (pause, step, "Show Cloth", ...); none means
        # anything to an operator of a tracker, so the panel holds the tracker's alone. Its option
        # handles go too: the viewer syncs whatever it still holds there on every frame.
        self.server.gui.reset()
        self.viewer._viewer_option_handles.clear()
        self.viewer._simulation_gui_handles.clear()
        self.choice = self.server.gui.add_dropdown("session", options=("none",), initial_value="none")
        self._panel = self.server.gui.add_markdown("No session is tracking.")
        self.server.gui.add_markdown(_LEGEND)
        self._estimate = self.server.scene.add_frame("/inhand/estimate", axes_length=0.04, axes_radius=0.002)
        self._estimate.visible = False
        self._marks: dict[str, object] = {}
        """The scene nodes drawn beside the worlds (the real fingertips, the 95 % region, its label)."""
        self._look_at = np.zeros(3)
        self._aimed: set[int] = set()
        self._aim_at_estimate = False
        self.model = self.state = None
        self.bodies = 0

    @property
    def port(self) -> int:
        return self.server.get_port()

    def clients(self) -> int:
        """How many browsers are connected; a new one is pointed at the object."""
        clients = self.server.get_clients()
        if clients.keys() - self._aimed:  # after the viewer's own set-up, which places the camera
            self.viewer.set_camera(wp.vec3(*(self._look_at + _CAMERA_OFFSET)), pitch=-25.0, yaw=135.0)
            self._aimed = set(clients)
        return len(clients)

    def show(self, robot, obj, config, K: int) -> None:
        """A new session or group: a replica of its K worlds, overlaid in place."""
        from inhand_tracker.sim_backend.build import build_model

        cfg = dataclasses.replace(config, groups=1, worlds=K, device="cpu")
        built = build_model(robot, obj, cfg, wp.get_device("cpu"))
        self.model, self.bodies = built.model, built.bodies
        self.state = self.model.state()
        self.viewer.set_model(self.model)
        self.viewer.show_collision = True  # the population's shapes are collision shapes, what the physics sees
        self.viewer.set_world_offsets((0.0, 0.0, 0.0))
        shape_body = self.model.shape_body.numpy()
        link = shape_body % built.bodies
        mine = (shape_body >= 0) & (link == built.object_body)
        opacity = self.model.shape_opacity.numpy()
        opacity[(shape_body >= 0) & ~mine] = _HAND_OPACITY
        self.model.shape_opacity.assign(opacity)
        colour = self.model.shape_color.numpy()
        colour[shape_body >= 0] = _LINK_PALETTE[link[shape_body >= 0] % len(_LINK_PALETTE)]
        colour[mine] = _OBJECT_COLOUR
        self.model.shape_color.assign(colour)
        self._aim_at_estimate = True  # every open browser turns to this object at its first estimate
        self._object_shapes = np.flatnonzero(mine)
        self._object_worlds = self.model.shape_world.numpy()[self._object_shapes]

    def draw(self, body_q: np.ndarray, weights: np.ndarray, tips: np.ndarray, estimate: EstimateView | None,
             text: str, sessions: tuple[str, ...]) -> None:  # fmt: skip
        """One snapshot: the worlds' bodies ``body_q`` (K * bodies * 7,), each object faded by its
        weight (K,), the real fingertips (L, 3) [m], the estimate, the panel's text and the
        sessions the browser may pick."""
        self.panel(text, sessions)
        if self.model is None:
            return
        opacity = self.model.shape_opacity.numpy()
        share = weights / max(float(weights.max()), 1e-12)
        opacity[self._object_shapes] = _FAINTEST + (_OBJECT_OPACITY - _FAINTEST) * share[self._object_worlds]
        self.model.shape_opacity.assign(opacity)
        self.state.body_q.assign(body_q.reshape(-1, 7))
        self.viewer.begin_frame(time.monotonic())
        self.viewer.log_state(self.state)
        self.viewer.end_frame()
        self._marks["tips"] = self.server.scene.add_point_cloud(
            "/inhand/real_fingertips", points=tips, colors=(220, 20, 60), point_size=0.012, point_shape="circle"
        )
        if estimate is not None:
            self._show_estimate(estimate)

    def panel(self, text: str, sessions: tuple[str, ...]) -> None:
        """The panel's text and the sessions the browser may pick."""
        if tuple(self.choice.options) != sessions:
            self.choice.options = sessions
        if self._panel.content != text:
            self._panel.content = text

    def _show_estimate(self, estimate: EstimateView) -> None:
        p = estimate.pose.astype(np.float64)
        self._look_at = p[:3]  # where a new browser looks
        if self._aim_at_estimate:  # a new session: the browsers already open turn to its object too
            self._aimed.clear()
            self._aim_at_estimate = False
        self._estimate.position, self._estimate.wxyz = p[:3], (p[6], p[3], p[4], p[5])
        self._estimate.visible = True
        # The region is around the estimate, where the object is drawn: the covariance is about the
        # weighted mean, so the mean's offset from the estimate is added to it (the second moment
        # about the estimate); a sphere at the mean sat beside the object when the two parted.
        centre = p[:3]
        offset = estimate.mean.astype(np.float64) - centre
        spread = estimate.covariance.astype(np.float64) + np.outer(offset, offset)
        radius = float(np.sqrt(_CHI2_3_95 * np.linalg.eigvalsh(spread).max()))
        self._marks["region"] = self.server.scene.add_icosphere(  # the same name replaces the last one
            "/inhand/mean_95", radius=max(radius, 1e-4), color=(255, 140, 0), opacity=0.45, position=centre
        )
        # A label draws over everything: the region's size reads even where the sphere is small.
        above = centre + np.array([0.0, 0.0, radius + 0.01])
        self._marks["label"] = self.server.scene.add_label(
            "/inhand/mean_95_label", f"95 %: {radius * 1e3:.1f} mm", position=above
        )

    def warm(self, robot, obj, config) -> None:
        """Show and draw one world once, so that a browser's first drawing compiles nothing."""
        self.show(robot, obj, config, 1)
        self.draw(self.state.body_q.numpy().ravel(), np.ones(1), np.zeros((0, 3)), None, "No session is tracking.",
                  ("none",))  # fmt: skip
        self.clear()

    def clear(self) -> None:
        """Nothing in the scene: before any session, and once the one shown has closed."""
        if self.model is not None:
            self.viewer.clear_model()
        for mark in self._marks.values():
            mark.remove()
        self._marks.clear()
        self._estimate.visible = False
        self.model = self.state = None

    def close(self) -> None:
        self.server.stop()


class _Shared:
    """The service's shared buffer, attached by name."""

    def __init__(self, name: str, size: int):
        # Attaching registers the segment with the resource tracker a second time; that tracker is
        # the service's (a spawned process shares its parent's), so the service's unlink clears it.
        self.memory = shared_memory.SharedMemory(name=name)
        self.array = np.ndarray((size,), np.float32, buffer=self.memory.buf)

    def close(self) -> None:
        del self.array
        self.memory.close()


def draw_forever(conn: Connection, host: str, port: int) -> None:
    """The drawing process's body: answers :class:`.Ready` (with its port) or :class:`.Failed`,
    then draws what the service sends (:mod:`.view_messages`) until the pipe closes."""
    import inhand_tracker.sim_backend  # noqa: F401  (first: Warp's adjoints off, as the service has them)
    from inhand_tracker.service.logs import quiet_warp, setup_logging

    setup_logging("WARNING")
    quiet_warp()
    # Drawing is worth less than tracking: on a machine with few cores it runs only on a core the
    # service's loop leaves idle (a niced process still takes its share of a busy core, late frames
    # on 2 cores).
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except OSError:  # a sandbox that refuses the policy: the lowest priority it allows
        os.nice(19)
    try:
        drawing = Drawing(host, port)
    except Exception as exc:
        conn.send(Failed(f"{type(exc).__name__}: {exc}"))
        return
    conn.send(Ready(drawing.port))
    shared: _Shared | None = None
    places: dict[str, tuple[int, int]] = {}
    told = None
    try:
        while True:
            if conn.poll(_POLL_S):
                match conn.recv():
                    case Close():
                        return
                    case Warm(robot, obj, config):
                        drawing.warm(robot, obj, config)
                    case Show(robot, obj, config, K, memory, sensors):
                        if shared is not None:
                            shared.close()
                        drawing.show(robot, obj, config, K)
                        places = layout(K, drawing.bodies, sensors)
                        shared = _Shared(memory, max(stop for _, stop in places.values()))
                    case Panel(text, sessions):
                        drawing.panel(text, sessions)
                        if sessions == ("none",):  # the session shown closed, and none is left
                            drawing.clear()
                    case Draw(estimate, text, sessions) if shared is not None:
                        part = {n: shared.array[a:b] for n, (a, b) in places.items()}
                        tips = part["tips"].reshape(-1, 3)
                        drawing.draw(part["body_q"], part["weights"], tips, estimate, text, sessions)
                told = (drawing.choice.value, drawing.clients())
                conn.send(Drawn(*told, done=True))
            elif (now := (drawing.choice.value, drawing.clients())) != told:
                told = now
                conn.send(Drawn(*told, done=False))
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        pass  # the service is gone
    except Exception as exc:
        log.exception("the live view failed to draw")
        with contextlib.suppress(OSError):
            conn.send(Failed(f"{type(exc).__name__}: {exc}"))
    finally:
        if shared is not None:
            shared.close()
        drawing.close()
