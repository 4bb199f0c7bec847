"""ROS 2 robots without a client: the sessions of the service's ``[[ros2_sessions]]``, fed from the
robot's own topics on the rmw_zenoh wire the service already speaks (:mod:`.ros2`).

A joint state is the robot's frame clock: each one becomes a frame with the latest command,
fingertip wrenches and touch that arrived before it. The first one opens the session, at its joint
positions, with the object at the config's ``p0`` (or the camera's latest pose); frames that arrive
while the population builds are queued, and a joint state after the session closed (its robot was
silent past the idle timeout) opens it again. A message that does not fit the robot (joints missing,
the wrong length) is said once in the log and counted in the session's status, never guessed at.

Messages are decoded on Zenoh's threads and applied on the service's loop, like a client's frames.
"""

from __future__ import annotations

import functools
import logging
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np
import zenoh

from inhand_tracker.protocol import Error, OpenSession, PoseObservation, RobotFrame, SessionInfo, checked
from inhand_tracker.service.tracker import METHODS

from .config import RosSession
from .outputs import Output
from .ros2 import TYPES, topic_key, topic_token

__all__ = ["ROS_PEER", "RosHost", "RosInputs", "check_sessions"]

log = logging.getLogger(__name__)

ROS_PEER = "ros2:"
"""The peer name of a ROS 2 session's opens is this and its name: its robot declares no liveliness
token of the service's protocol, so the session is held by its frames alone (the idle timeout)."""
JOINT_STATE = "sensor_msgs/msg/JointState"
WRENCH = "geometry_msgs/msg/WrenchStamped"
ARRAY = "std_msgs/msg/Float32MultiArray"
CAMERA = "geometry_msgs/msg/PoseWithCovarianceStamped"
_QUEUED = 256
"""Frames kept while a session's population builds; older ones are dropped (and said)."""
_RETRY_S = 5.0
"""A refused open is tried again on the first joint state this long after it."""


@dataclass(frozen=True)
class RosHost:
    """What the inputs ask of the service, on its loop thread."""

    post: Callable[..., None]
    """Queue work for the loop: ``post(name, run(done), done)``."""
    open: Callable[..., SessionInfo | None]
    """Open a session: ``open(request, notice, peer, done)``; None while its population builds."""
    frame: Callable[[RobotFrame, float], None]
    observation: Callable[[PoseObservation], None]


def check_sessions(specs: tuple[RosSession, ...], robots: dict, objects: dict) -> None:
    """A ValueError naming a declared session whose robot, object or method the service lacks."""
    for i, s in enumerate(specs):
        for key, known in (("robot", robots), ("object", objects), ("method", METHODS)):
            if (value := getattr(s, key)) not in known:
                raise ValueError(f"service config ros2_sessions[{i}].{key}: '{value}' is not one of {sorted(known)}")


def _stamp(header, received: float) -> float:
    """A header's time [s]; a zero stamp (a driver that leaves it unset) is when it arrived."""
    t = header.stamp.sec + header.stamp.nanosec * 1e-9
    return t if t > 0 else received


@dataclass
class _Feed:
    """One declared session's state between messages."""

    spec: RosSession
    session: str | None = None
    token: str = ""
    seq: int = 0
    opening: bool = False
    retry_at: float = 0.0
    joints: tuple[str, ...] = ()
    """The robot's joints, in its frames' order (from the robot's layout)."""
    sensors: int = 0
    zones: int = 0
    command: np.ndarray | None = None
    force: np.ndarray | None = None
    touch: np.ndarray | None = None
    camera: PoseObservation | None = None
    queued: deque = field(default_factory=lambda: deque(maxlen=_QUEUED))
    said: set[str] = field(default_factory=set)

    def say(self, problem: str) -> None:
        """Log a problem once per kind of problem: a stream repeats it every frame."""
        if problem not in self.said:
            self.said.add(problem)
            log.warning("ROS 2 session '%s': %s", self.spec.name, problem)

    def by_name(self, names, values, topic: str) -> np.ndarray | None:
        """``values`` in the robot's joint order, by the message's ``names`` (or in order when it names none)."""
        values = np.asarray(values, np.float32)
        if len(names) == 0:
            if len(values) == len(self.joints):
                return values
            return self.say(f"{topic}: {len(values)} unnamed positions for the robot's {len(self.joints)} joints")
        index = {n: i for i, n in enumerate(names)}
        missing = [j for j in self.joints if j not in index]
        if missing or len(values) != len(names):
            return self.say(f"{topic}: joints {missing} of the robot missing (has {list(names)})")
        return values[[index[j] for j in self.joints]]


class RosInputs(Output):
    """The subscriptions of every declared ROS 2 session, and their sessions' frames."""

    name = "ROS 2 inputs"

    def __init__(
        self, session: zenoh.Session, domain_id: int, specs: tuple[RosSession, ...], host: RosHost, namespace: str = "/"
    ):
        self.host, self.domain_id = host, domain_id
        self._feeds = {s.name: _Feed(s) for s in specs}
        self._layouts = None
        zid, self._entities, self._tokens, self._subscribers = str(session.info.zid()), 1000, [], []
        for feed in self._feeds.values():
            s = feed.spec
            topics = [(s.joint_states, JOINT_STATE, self._joint_state)]
            if s.commands:
                topics.append((s.commands, s.commands_type, self._command))
            topics += [(t, WRENCH, functools.partial(self._wrench, i)) for i, t in enumerate(s.wrenches)]
            if s.touch:
                topics.append((s.touch, ARRAY, self._touch))
            if s.camera:
                topics.append((s.camera, CAMERA, self._camera))
            for topic, msg_type, apply in topics:
                self._entities += 1
                token = topic_token(domain_id, zid, "inhand_tracker", namespace, self._entities, "MS", topic, msg_type)
                self._tokens.append(session.liveliness().declare_token(token))
                handler = functools.partial(self._on_sample, feed, topic, msg_type, apply)
                self._subscribers.append(session.declare_subscriber(topic_key(domain_id, topic, msg_type), handler))
        log.info("ROS 2 sessions %s read their robots' topics (domain %d)", sorted(self._feeds), domain_id)

    # ------------------------------------------------------------------ Zenoh's threads: decode, queue
    def _on_sample(self, feed: _Feed, topic: str, msg_type: str, apply, sample: zenoh.Sample) -> None:
        received = time.time()
        try:
            message = TYPES.deserialize_cdr(bytes(sample.payload.to_bytes()), msg_type)
        except Exception as exc:  # any undecodable payload is the sender's
            text = f"{topic}: not a {msg_type} ({type(exc).__name__}: {exc})"
            return self.host.post("bad ROS 2 input", lambda _: feed.say(text))
        self.host.post("ROS 2 input", lambda _: apply(feed, message, received))

    # ------------------------------------------------------------------ the loop's thread
    def warm(self, manager) -> None:
        for feed in self._feeds.values():
            s = feed.spec
            layout = manager.layout(s.robot)
            feed.joints, feed.sensors, feed.zones = layout.joint_names, len(layout.sensor_names), len(layout.zone_names)
            if s.wrenches and len(s.wrenches) != feed.sensors:
                feed.say(f"{len(s.wrenches)} wrench topics for the robot's {feed.sensors} fingertip sensors: unused")

    def _joint_state(self, feed: _Feed, msg, received: float) -> None:
        q = feed.by_name(msg.name, msg.position, feed.spec.joint_states)
        if q is None:
            return
        arrays = (_stamp(msg.header, received), q, feed.command if feed.command is not None else q)
        if feed.session is None:
            feed.queued.append(arrays)
            if not feed.opening and received >= feed.retry_at:
                self._open(feed, q)
            return
        self._send(feed, *arrays)

    def _send(self, feed: _Feed, stamp: float, q: np.ndarray, controls: np.ndarray) -> None:
        s = feed.spec
        force = None
        if s.wrenches and len(s.wrenches) == feed.sensors:
            force = feed.force if feed.force is not None else np.zeros((feed.sensors, 3), np.float32)
        touch = None
        if s.touch:
            touch = feed.touch if feed.touch is not None else np.zeros(feed.zones, np.float32)
        try:  # a value no robot sends (NaN from a driver) is refused with the field, once in the log
            frame = checked(
                RobotFrame, session=feed.session, seq=feed.seq, stamp=stamp, token=feed.token, controls=controls,
                q=q, force=force, touch=touch,
            )  # fmt: skip
        except ValueError as exc:
            return feed.say(f"frame refused: {exc}")
        feed.seq += 1
        try:
            self.host.frame(frame, time.perf_counter())
        except Exception as exc:  # a refused frame is counted in the session's status
            feed.say(f"frame refused: {exc}")

    def _open(self, feed: _Feed, q: np.ndarray) -> None:
        s = feed.spec
        p0 = feed.camera.pose if feed.camera is not None else np.asarray(s.p0, np.float32)
        request = OpenSession(
            robot=s.robot, object=s.object, p0=p0, sigma_t=s.sigma_t, sigma_r=s.sigma_r, q0=q, method=s.method,
            worlds=s.worlds, allow_fewer=True, name=s.name,
        )  # fmt: skip
        feed.opening = True
        done: Future = Future()
        done.add_done_callback(lambda f: self.host.post("ROS 2 open", lambda _: self._opened(feed, f.result())))
        self.host.post("open", functools.partial(self.host.open, request, None, ROS_PEER + s.name), done)

    def _opened(self, feed: _Feed, answer) -> None:
        feed.opening = False
        if isinstance(answer, Error):
            feed.retry_at = time.time() + _RETRY_S
            feed.queued.clear()
            name, why = feed.spec.name, answer.message
            log.error("ROS 2 session '%s' could not open: %s (tried again in %.0f s)", name, why, _RETRY_S)

    def open(self, info: SessionInfo, request: OpenSession) -> None:
        feed = self._feeds.get(info.name or "")
        if feed is None or not feed.opening:
            return
        feed.session, feed.token, feed.seq, feed.said = info.session, info.token, 0, set()
        log.info("ROS 2 session '%s' opened as %s (%d worlds)", info.name, info.session, info.worlds)
        while feed.queued:
            self._send(feed, *feed.queued.popleft())

    def drop(self, session: str) -> None:
        for feed in self._feeds.values():
            if feed.session == session:
                feed.session, feed.command, feed.force, feed.touch, feed.camera = None, None, None, None, None

    def _command(self, feed: _Feed, msg, received: float) -> None:
        if feed.spec.commands_type == JOINT_STATE:
            command = feed.by_name(msg.name, msg.position, feed.spec.commands)
        else:
            command = feed.by_name(feed.spec.command_joints, msg.data, feed.spec.commands)
        if command is not None:
            feed.command = command

    def _wrench(self, i: int, feed: _Feed, msg, received: float) -> None:
        if feed.force is None:
            feed.force = np.zeros((feed.sensors, 3), np.float32)
        if i < feed.sensors:
            f = msg.wrench.force
            feed.force[i] = (f.x, f.y, f.z)

    def _touch(self, feed: _Feed, msg, received: float) -> None:
        if len(msg.data) != feed.zones:
            return feed.say(f"{feed.spec.touch}: {len(msg.data)} values for the robot's {feed.zones} touch zones")
        feed.touch = np.asarray(msg.data, np.float32)

    def _camera(self, feed: _Feed, msg, received: float) -> None:
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        covariance = np.asarray(msg.pose.covariance, np.float64).reshape(6, 6)
        if not covariance.any():
            t, r = feed.spec.camera_sigma
            covariance = np.diag([t * t] * 3 + [r * r] * 3)
        try:
            observation = PoseObservation(
                session=feed.session or "", token=feed.token, stamp=_stamp(msg.header, received),
                pose=np.array([p.x, p.y, p.z, o.x, o.y, o.z, o.w], np.float32), covariance=covariance,
            )  # fmt: skip
        except ValueError as exc:
            return feed.say(f"{feed.spec.camera}: {exc}")
        feed.camera = observation
        if feed.session is not None:
            try:
                self.host.observation(observation)
            except Exception as exc:  # counted in the session's status
                feed.say(f"camera pose refused: {exc}")

    def close(self) -> None:
        for entity in self._subscribers + self._tokens:
            entity.undeclare()
