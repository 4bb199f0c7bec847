"""``TrackerClient``: open a tracking session, stream robot frames, read the estimates."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable

import numpy as np
import zenoh
from pydantic import BaseModel

from inhand_tracker.protocol import (
    AUTO,
    DEFAULT_METHOD,
    CloseSession,
    DecodeError,
    Error,
    ErrorCode,
    Estimate,
    Keys,
    OpenSession,
    PoseObservation,
    RobotFrame,
    ServiceInfo,
    SessionInfo,
    SessionStatus,
    checked,
    decode,
    encode,
)
from inhand_tracker.protocol.auth import sign, signed_query

from .builds import BuildWatch
from .errors import ServiceLost, StaleEstimate, TrackerError
from .trust import Trust
from .zenoh_session import connected, zenoh_config, zenoh_encoding

__all__ = ["ServiceLost", "StaleEstimate", "TrackerClient", "TrackerError"]

_NO_LINK_S = 0.8
"""How long a client waits for a link at its connect endpoints before it says nothing is there [s]."""


class TrackerClient:
    """A connection to a tracking service; one session at a time. Without a service name, each
    open goes to the ready service with the most room on the Zenoh network (several services,
    one per GPU or host, behind one router).

    >>> with TrackerClient(connect=["tcp/127.0.0.1:7447"]) as client:
    ...     client.open_session("allegro", "foam_brick", p0)
    ...     client.send_frame(controls, q, force=force)
    ...     pose = client.latest_pose(timeout=1.0)
    """

    def __init__(
        self,
        connect=("tcp/127.0.0.1:7447",),
        service: str | None = "default",
        listen=(),
        scouting: bool = False,
        timeout: float = 120.0,
        zenoh_file: str | os.PathLike | None = None,
        open_timeout: float = 900.0,
        peer: str | None = None,
        zenoh_mode: str | None = None,
        service_key: str | None = None,
        identity: str | os.PathLike | None = None,
    ):
        """``service``: its name, or None to choose at each open. ``zenoh_file``: a Zenoh JSON5 config
        (TLS or mTLS certificates) under the endpoints given. ``open_timeout``: an open's wait [s].
        ``zenoh_mode``: "client" behind a router that relays nothing between peers (rmw_zenoh's);
        None: the file's mode, else peer. ``service_key``: the service's key fingerprint, as
        ``serve`` prints it (or the key): its info, open reply and estimates are then checked.
        ``identity``: a file with this robot's own key (made on first use): each open proves it, and
        the service knows the robot by it (its caps, names, and room kept: ``robot_keys``).
        ``peer``: the name to open under (behind the hardened router, the certificate's name)."""
        self._route, self.peer = service is None, peer
        self.keys = Keys(service or "default", peer)
        self.endpoints = list(connect) or ["(scouting)"]
        """Where this client looks for its service, for the errors that say it found none."""
        self._connects = bool(connect)
        self.timeout, self.open_timeout = timeout, open_timeout
        self._zenoh = zenoh.open(zenoh_config(listen, connect, scouting, zenoh_file, zenoh_mode))
        self.trust = Trust(service_key, identity)
        self.info: SessionInfo | None = None
        self._seq = 0
        self._epoch = 0
        """Restarts of the seq counter in this session: the service re-synchronises only to a newer one."""
        self._publisher: zenoh.Publisher | None = None
        self._token = None
        self._subscriber = None
        self._latest: Estimate | None = None
        self._new = threading.Condition()
        self._callbacks: list[Callable[[Estimate], None]] = []
        self._sent_stamp: float | None = None  # the robot clock of the newest frame sent [s]
        self._opened: dict | None = None  # the last open_session's arguments, for :meth:`reopen`
        self._service_watch = None
        self._observer: zenoh.Publisher | None = None
        self.service_lost = False
        """Set when the service's liveliness token went away while a session was open."""

    # ------------------------------------------------------------------ requests
    def _get(self, key: str, request: BaseModel | None, model, timeout: float | None = None):
        payload = {} if request is None else {"payload": encode(request), "encoding": zenoh_encoding(type(request))}
        replies = self._zenoh.get(key, timeout=timeout or self.timeout, **payload)
        for reply in replies:
            if reply.ok is not None:
                return decode(bytes(reply.ok.payload.to_bytes()), model)
            raw = bytes(reply.err.payload.to_bytes())
            try:
                err = decode(raw, Error)
            except DecodeError:
                # Not the service's: Zenoh's own (a query that timed out says "Timeout").
                text = raw.decode("utf-8", "replace")
                if "timeout" in text.lower():
                    raise TimeoutError(f"{key}: no reply from service '{self.keys.service}': {text}") from None
                raise TrackerError(ErrorCode.INTERNAL, f"{key}: unreadable error reply: {text!r}") from None
            raise TrackerError(err.code, err.message, err.others)
        raise TimeoutError(f"{key}: no reply from service '{self.keys.service}' within {timeout or self.timeout} s")

    def service_info(self, timeout: float = 5.0) -> ServiceInfo:
        return self.trust.info(self._get(self.keys.info, None, ServiceInfo, timeout))

    def services(self, timeout: float = 2.0) -> list[ServiceInfo]:
        """Every service that answers on this Zenoh network, the roomiest first (free worlds, sessions)."""
        replies = self._zenoh.get(
            Keys.services("info"),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout,
        )
        found = {}
        for reply in replies:
            if reply.ok is not None:
                with contextlib.suppress(DecodeError):
                    info = decode(bytes(reply.ok.payload.to_bytes()), ServiceInfo)
                    found[info.name] = info
        return sorted(found.values(), key=lambda i: (-i.free_worlds, i.sessions - i.max_sessions, i.name))

    def wait_ready(
        self, timeout: float | None = None, absent: float | None = None, waiting: Callable[[float], None] | None = None
    ) -> ServiceInfo:
        """Wait until the service (without a name: any service) answers and has compiled its
        kernels (minutes on a first start with a cold cache); TimeoutError after ``timeout`` [s]
        (default the client's), or, with ``absent``, after that many seconds in which nothing
        answered at all: a service warming up answers that it is not ready, one that is not there
        never answers (a service process still importing its libraries does not answer either).
        ``waiting(seconds)`` is called on every poll while a service answers but is not ready."""
        start = time.monotonic()
        deadline = start + (timeout or self.timeout)
        answered = False
        while True:
            linked = connected(self._zenoh)
            if absent is not None and not linked and self._connects and time.monotonic() - start >= _NO_LINK_S:
                which = "no service" if self._route else f"service '{self.keys.service}'"
                raise TimeoutError(
                    f"{which} does not answer at {', '.join(self.endpoints)}: nothing is there (no router or"
                    f" service reached in {_NO_LINK_S:g} s); start one with `inhand-tracker serve`, or give its"
                    " address (--connect)"
                )
            # Short polls while no link is up, so that an absent router is said within a second.
            left = min(2.0 if linked else 0.25, max(0.1, deadline - time.monotonic()))
            try:
                if self._route:
                    found = self.services(timeout=left)
                    answered |= bool(found)
                    if ready := [i for i in found if i.ready]:
                        return ready[0]
                else:
                    info = self.service_info(timeout=left)
                    answered = True
                    if info.ready:
                        return info
            except TimeoutError:
                pass
            which = "no service" if self._route else f"service '{self.keys.service}'"
            if absent is not None and not answered and time.monotonic() - start >= absent:
                raise TimeoutError(
                    f"{which} does not answer at {', '.join(self.endpoints)} (waited {absent:g} s): start one"
                    " with `inhand-tracker serve`, or give its address (--connect) and name (--name)"
                )
            if time.monotonic() >= deadline:
                raise TimeoutError(f"{which} ready within {timeout or self.timeout} s")
            if answered and waiting is not None:
                waiting(time.monotonic() - start)
            time.sleep(0.2)

    def open_session(
        self,
        robot: str,
        object: str,
        p0,
        *,
        sigma_t: float = 0.005,
        sigma_r: float = 0.1,
        q0=None,
        method: str = DEFAULT_METHOD,
        worlds: int | str = AUTO,
        allow_fewer: bool = False,
        overrides: dict[str, float] | None = None,
        name: str | None = None,
    ) -> SessionInfo:
        """Ask the service to track ``object`` in ``robot``'s hand from the pose estimate ``p0`` (7,).

        ``worlds``: K, or "auto" for the most the service's frame budget allows now;
        ``allow_fewer``: take fewer than K when the budget has no room for K, instead of a refusal
        (:attr:`SessionInfo.notice` says why); ``name``: the session's ROS 2 topics and TF frame
        (``/inhand/{name}/pose``; default ``{robot}_{object}``)."""
        if self.info is not None:
            raise RuntimeError(f"session '{self.info.session}' is open; close it first")
        # A service compiling on a cold cache is waited for as long as a build; an absent one is said at once.
        service = self.wait_ready(self.open_timeout, absent=3.0)
        request = checked(
            OpenSession,
            robot=robot,
            object=object,
            p0=np.asarray(p0, np.float32),
            sigma_t=sigma_t,
            sigma_r=sigma_r,
            q0=None if q0 is None else np.asarray(q0, np.float32),
            method=method,
            worlds=worlds,
            allow_fewer=allow_fewer,
            overrides=overrides or {},
            name=name,
        )
        self.info = info = self.trust.opened(self._open(request, service))
        self._opened = dict(robot=robot, object=object, p0=p0, sigma_t=sigma_t, sigma_r=sigma_r, q0=q0,
                            method=method, worlds=worlds, allow_fewer=allow_fewer, overrides=overrides,
                            name=name)  # fmt: skip
        self._seq = self._epoch = 0
        self._latest = None
        self._sent_stamp = None
        self.service_lost = False
        # Frames and observations share one priority and congestion control: Zenoh keeps the order within
        # a priority on a link, so an observation sent before a frame is used at that frame, and none is
        # dropped on a busy link. Both are declared here: one declared at the first observation could be overtaken.
        ordered = dict(
            express=True, priority=zenoh.Priority.REAL_TIME, congestion_control=zenoh.CongestionControl.BLOCK
        )
        self._publisher = self._zenoh.declare_publisher(
            self.keys.frame(info.session), encoding=zenoh_encoding(RobotFrame), **ordered
        )
        self._observer = self._zenoh.declare_publisher(
            self.keys.observation(info.session), encoding=zenoh_encoding(PoseObservation), **ordered
        )
        self._subscriber = self._zenoh.declare_subscriber(self.keys.pose(info.session), self._on_pose)
        self._token = self._zenoh.liveliness().declare_token(self.keys.robot(info.session))
        self._service_watch = self._zenoh.liveliness().declare_subscriber(self.keys.alive, self._on_service)
        self.trust.watch(self._zenoh, self.keys.beat)
        return info

    def _open(self, request: OpenSession, service: ServiceInfo) -> SessionInfo:
        """Open at the named service; else at the roomiest ready one, the next while they say
        ``capacity``; each open is proven to the service it goes to."""
        with BuildWatch(self.service_info):  # an open waits for its population's build, and says so
            if not self._route:
                return self._get(self.keys.open, self.trust.request(request, service), SessionInfo, self.open_timeout)
            full: TrackerError | None = None
            for info in (i for i in self.services() if i.ready):
                self.keys = Keys(info.name, self.peer)
                try:
                    return self._get(self.keys.open, self.trust.request(request, info), SessionInfo, self.open_timeout)
                except TrackerError as exc:
                    if exc.code != ErrorCode.CAPACITY:
                        raise
                    full = exc
            raise full or TimeoutError("no ready service answered")

    def reopen(self, p0=None, q0=None) -> SessionInfo:
        """Open a new session like the last one, from ``p0`` (default: the last estimate, else the
        first open's pose) after the service restarted or the session was closed."""
        if self._opened is None:
            raise RuntimeError("no session was ever opened: call open_session first")
        args = dict(self._opened)
        if p0 is not None:
            args["p0"] = p0
        elif self._latest is not None:
            args["p0"] = self._latest.pose
        if q0 is not None:
            args["q0"] = q0
        self._release()
        return self.open_session(**args)

    def _on_service(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            with self._new:
                self.service_lost = True
                self._new.notify_all()

    def send_frame(
        self, controls, q, *, stamp: float | None = None, seq: int | None = None, **touch: np.ndarray | None
    ) -> int:
        """Send one frame: joint targets ``controls`` and positions ``q`` (D,), and the optional
        touch fields of ``protocol.SENSING`` by name (force=(L, 3), slip=(L,), ...); returns its seq."""
        if self.info is None:
            raise RuntimeError("no session: call open_session first")
        seq = self._seq if seq is None else seq
        frame = RobotFrame(
            session=self.info.session,
            seq=seq,
            stamp=float(seq / 30.0 if stamp is None else stamp),
            controls=controls,
            q=q,
            **{name: value for name, value in touch.items() if value is not None},
        )
        self.send(frame)
        return seq

    def observe_pose(self, pose, covariance, stamp: float | None = None) -> None:
        """Send the object's pose as another sensor saw it (a vision pose estimator): ``pose`` (7,)
        position [m] and quaternion (x, y, z, w) in the robot's world frame, ``covariance`` (6, 6)
        of position [m^2] and rotation vector [rad^2]; ``stamp``: the robot clock when it was seen
        [s] (default: the newest frame's). At any rate; late by up to the service's
        ``max_observation_age_s``. Raises pydantic's ValidationError on a malformed one."""
        if self.info is None:
            raise RuntimeError("no session: call open_session first")
        observation = PoseObservation(
            session=self.info.session,
            stamp=float(stamp if stamp is not None else (self._sent_stamp or 0.0)),
            pose=pose,
            covariance=covariance,
        )
        self._observer.put(encode(sign(observation, self.info.token)))

    def send(self, frame: RobotFrame) -> None:
        """Send a prepared frame (its session and epoch are replaced by this client's, and it is
        signed). A seq below the last one sent restarts the counter: a new epoch, which the service
        follows, while a replay of the old frames is refused (the last seq again is a duplicate)."""
        if frame.seq < self._seq - 1:
            self._epoch += 1
        update = {"session": self.info.session, "epoch": self._epoch}
        self._publisher.put(encode(sign(frame.model_copy(update=update), self.info.token)))  # the token never travels
        self._seq = frame.seq + 1
        self._sent_stamp = frame.stamp

    def _on_pose(self, sample: zenoh.Sample) -> None:
        estimate = decode(bytes(sample.payload.to_bytes()), Estimate)
        if self.info is None or not self.trust.estimate(estimate, self.info.token):
            return
        with self._new:
            self._latest = estimate
            self._new.notify_all()
        for callback in list(self._callbacks):
            callback(estimate)

    def on_pose(self, callback: Callable[[Estimate], None]) -> None:
        """Call ``callback(estimate)`` for every estimate (on a Zenoh thread: keep it short)."""
        self._callbacks.append(callback)

    def remove_pose_callback(self, callback: Callable[[Estimate], None]) -> None:
        self._callbacks.remove(callback)

    def latest_pose(self, timeout: float = 1.0, after_seq: int | None = None, max_age: float | None = None) -> Estimate:
        """The newest estimate; with ``after_seq``, wait until one for that seq or later arrives.

        ``max_age`` [s]: raise :class:`StaleEstimate` when the estimate answers a frame older, by
        the robot's clock, than the newest frame sent by more than this. :class:`ServiceLost` when
        the service went away while the session was open."""

        def done() -> bool:
            new = self._latest is not None and (after_seq is None or self._latest.seq >= after_seq)
            return new or self.service_lost or not self.trust.alive()

        with self._new:
            end = time.monotonic() + timeout  # in slices: a service whose beats stop notifies nobody
            while not (ok := self._new.wait_for(done, min(0.25, end - time.monotonic()))) and time.monotonic() < end:
                pass
            if self.service_lost or not self.trust.alive():  # its token withdrawn, or its beats stopped
                raise ServiceLost(f"service '{self.keys.service}' went away; session '{self._session_id()}' is gone")
            estimate = self._latest if ok else None
        if estimate is None:
            if self.info is None:
                raise RuntimeError("no session: call open_session first")
            got = self._get(self.keys.pose(self.info.session), None, Estimate, timeout)
            estimate = self.trust.checked(got, self.info.token)
        if max_age is not None and self._sent_stamp is not None and self._sent_stamp - estimate.stamp > max_age:
            raise StaleEstimate(
                f"the newest estimate answers seq {estimate.seq} (stamp {estimate.stamp:.3f} s), "
                f"{self._sent_stamp - estimate.stamp:.3f} s behind the last frame sent (seq {self._seq - 1}); "
                f"allowed {max_age} s"
            )
        return estimate

    def poses(self, timeout: float = 2.0) -> dict[str, Estimate]:
        """The latest estimate of every session of the service that has one, by session (a
        watcher's view; no session of its own needed)."""
        out = {}
        for reply in self._zenoh.get(self.keys.every("pose"), target=zenoh.QueryTarget.ALL, timeout=timeout):
            if reply.ok is not None:
                estimate = decode(bytes(reply.ok.payload.to_bytes()), Estimate)
                out[estimate.session] = estimate
        return out

    def watch(self, callback: Callable[[Estimate], None]) -> zenoh.Subscriber:
        """Call ``callback(estimate)`` for every estimate of every session of the service (a
        dashboard, a logger; on a Zenoh thread: keep it short). Undeclare the returned subscriber
        to stop."""

        def deliver(sample: zenoh.Sample) -> None:
            callback(decode(bytes(sample.payload.to_bytes()), Estimate))

        return self._zenoh.declare_subscriber(self.keys.every("pose"), deliver)

    def _session_id(self) -> str | None:
        return self.info.session if self.info is not None else None

    def status(self, timeout: float = 5.0) -> SessionStatus:
        if self.info is None:
            raise RuntimeError("no session: call open_session first")
        return self._get(self.keys.status(self.info.session), self._credentials("status"), SessionStatus, timeout)

    def _credentials(self, purpose: str) -> CloseSession:
        """The payload that proves a ``purpose`` request comes from this session's robot: signed,
        so that a peer answering in the service's place learns nothing it could use."""
        return signed_query(CloseSession(session=self.info.session), self.info.token, purpose)

    def close_session(self) -> None:
        if self.info is None:
            return
        try:
            self._get(self.keys.close, self._credentials("close"), CloseSession, 10.0)
        finally:
            self._release()

    def _release(self) -> None:
        """Forget the session on this side: its token, subscribers and publisher."""
        for entity in (self._token, self._subscriber, self._publisher, self._service_watch, self._observer):
            if entity is not None:
                entity.undeclare()
        self._token = self._subscriber = self._publisher = self._service_watch = self._observer = None
        self.info = None

    def close(self) -> None:
        """Close the session (if any) and leave Zenoh."""
        try:
            self.close_session()
        except (TrackerError, TimeoutError):
            pass  # the service is gone or forgot us: nothing left to close
        finally:
            self._zenoh.close()

    def __enter__(self) -> TrackerClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
