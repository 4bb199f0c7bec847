"""The service on Zenoh: handlers that only decode, validate and queue, one loop thread that
owns the GPU (the :class:`SessionManager`) and publishes every estimate, and a builder thread
that builds new populations between the loop's steps, so that an open never freezes the others.

Keys (protocol/keys.py): a liveliness token ``alive``; queryables ``info``, ``rpc/open``,
``rpc/close``, ``s/*/pose`` (latest estimate) and ``s/*/status``; one subscriber on ``s/*/*`` for
the robots' frames and observations, in the order they arrive; a liveliness subscriber on
``s/*/robot`` that closes a session whose robot is gone past the timeout.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import queue
import threading
import time
from concurrent.futures import Future, InvalidStateError, ThreadPoolExecutor

import zenoh

from client import zenoh_config, zenoh_encoding
from protocol import (
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
    decode,
    encode,
)
from service.paths import resolve
from service.tracker import METHODS
from sim_backend import load_catalog, load_robot, resolve_device

from .config import ServiceConfig
from .recording import SessionRecorder
from .ros2 import RosTopics
from .sessions import Admission, ServiceError, SessionManager

__all__ = ["TrackerNode"]

log = logging.getLogger(__name__)

_ESTIMATE = zenoh_encoding(Estimate)
_STALL_S = 1.0
"""A turn of the service's loop longer than this [s] was the service's own stall: the sessions'
idle time counts again from its end."""


def _guarded(handler):
    """A Zenoh callback that raises is printed to stderr by Zenoh, past the service's log, and its
    query is left unanswered until the client times out: log it, and answer with the reason."""

    @functools.wraps(handler)
    def run(self, arg) -> None:
        try:
            handler(self, arg)
        except Exception as exc:
            log.exception("%s on %s failed", handler.__name__, getattr(arg, "key_expr", "?"))
            if isinstance(arg, zenoh.Query):
                error = encode(Error(code=ErrorCode.INTERNAL, message=f"{type(exc).__name__}: {exc}"))
                # A query answered before it raised takes no more; `with` finalises it now (the
                # traceback holds it, so the client would wait for its timeout).
                with contextlib.suppress(Exception), arg:
                    arg.reply_err(error, encoding=zenoh_encoding(Error))

    return run


class TrackerNode:
    """The long-running tracking service of one process."""

    def __init__(self, config: ServiceConfig):
        self.config = config
        self.keys = Keys(config.name)
        robots = {}
        for path in config.robots:
            spec = load_robot(resolve(path))
            robots[spec.name] = spec
        self.device = str(resolve_device(config.device))
        self.manager = SessionManager(config, robots, load_catalog(resolve(config.objects)))
        self._inbox: queue.Queue = queue.Queue()
        self._latest: dict[str, bytes] = {}
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._robot_gone: dict[str, float] = {}
        self._stop = threading.Event()
        self.failed = threading.Event()
        """Set when the loop thread died: the service withdrew its liveliness token and must exit."""
        self._loop = threading.Thread(target=self._guarded_run, name="inhand-gpu-loop", daemon=True)
        self.ready = False
        """Kernels compiled and the liveliness token declared: sessions may open."""
        self._beat = time.monotonic()
        """When the loop last came round [s, monotonic]."""
        self._in_flight: Future | None = None
        """The request the loop is handling now."""
        self._builder = ThreadPoolExecutor(max_workers=1, thread_name_prefix="inhand-build")
        """Builds populations off the loop thread."""
        self._waiting: dict[tuple, list[tuple[OpenSession, Future | None, str | None]]] = {}
        """Opens waiting for their population's build, by population key: the request with the
        worlds granted, and why fewer than asked (when so)."""
        self._token = None
        self.session: zenoh.Session | None = None
        self._others: set[str] = set()
        """The other services on this Zenoh network (their liveliness tokens): named to a robot
        this one has no room for."""
        self._room = (0.0, 0)
        """The loop's latest (load_ms, free_worlds), for the info queryable."""
        self._ros: RosTopics | None = None
        """The sessions' estimates as ROS 2 topics (setting ``ros2``)."""
        self._recorder = SessionRecorder(config.record, config.name, config.ros2_frame_id) if config.record else None
        """Every session recorded to MCAP (setting ``record``)."""
        self._view = None
        """The live view in a browser (setting ``view_port``)."""

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> TrackerNode:
        cfg, keys = self.config, self.keys
        file = resolve(cfg.zenoh_config) if cfg.zenoh_config else None
        self.session = s = zenoh.open(zenoh_config(cfg.listen, cfg.connect, cfg.scouting, file))
        self._entities = [
            s.declare_queryable(keys.info, self._on_info),
            s.declare_queryable(keys.open, self._on_open),
            s.declare_queryable(keys.close, self._on_close),
            s.declare_queryable(keys.every("pose"), self._on_pose),
            s.declare_queryable(keys.every("status"), self._on_status),
            # One subscriber for what robots publish: zenoh-python runs each subscriber's callback
            # on a thread of its own, so with one for frames and one for observations a frame could
            # reach the tracker before an observation that arrived ahead of it on the link. Remote
            # only: the session's keys also carry this service's own estimates.
            s.declare_subscriber(keys.every("*"), self._on_robot_sample, allowed_origin=zenoh.Locality.REMOTE),
            s.liveliness().declare_subscriber(keys.every("robot"), self._on_robot, history=True),
            s.liveliness().declare_subscriber(Keys.services("alive"), self._on_service, history=True),
        ]
        if cfg.ros2:
            self._ros = RosTopics(s, cfg.ros2_domain_id, cfg.ros2_frame_id, cfg.ros2_tf)
        if cfg.view_port:
            from .viewer import LiveView  # viser, only where a view is asked for

            self._view = LiveView(cfg.view_host, cfg.view_port)
        self._loop.start()  # it warms up, then declares the service's liveliness token
        self._watchdog = threading.Thread(target=self._watch, name="inhand-watchdog", daemon=True)
        self._watchdog.start()
        return self

    def close(self) -> None:
        """Stop the loop, close every session, leave Zenoh."""
        self._stop.set()
        if self._loop.is_alive():
            self._loop.join(timeout=10)
        # A loop still busy (a population build) or dead leaves requests unanswered, and Zenoh's
        # close waits for the handlers that wait on them: answer them, so the service can go.
        self._builder.shutdown(wait=False, cancel_futures=True)
        pending = [self._in_flight, *(done for waits in self._waiting.values() for _, done, _ in waits)]
        while not self._inbox.empty():
            pending.append(self._inbox.get_nowait()[2])
        for done in pending:
            _answer(done, Error(code=ErrorCode.INTERNAL, message="the service is stopping"))
        if self._recorder is not None:
            self._recorder.close_all()
        if self._ros is not None:
            self._ros.close()
            self._ros = None
        if self._view is not None:
            self._view.close()
            self._view = None
        if self.session is not None:
            self.session.close()
            self.session = None

    def __enter__(self) -> TrackerNode:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ zenoh handlers (decode, queue)
    def _call(self, kind: str, payload) -> object:
        """Hand a request to the loop and wait for its answer (opening may build a population)."""
        done: Future = Future()
        self._inbox.put((kind, payload, done))
        return done.result(timeout=300)

    def _reply(self, query: zenoh.Query, answer) -> None:
        with query:
            if isinstance(answer, Error):
                query.reply_err(encode(answer), encoding=zenoh_encoding(Error))
            else:
                query.reply(query.key_expr, encode(answer), encoding=zenoh_encoding(type(answer)))

    @_guarded
    def _on_info(self, query: zenoh.Query) -> None:
        m = self.manager
        info = ServiceInfo(
            name=self.config.name,
            device=self.device,
            robots=sorted(m.robots),
            objects=sorted(m.objects),
            methods=list(METHODS),
            groups=self.config.groups,
            max_worlds=self.config.max_worlds,
            sessions=len(m.sessions),
            max_sessions=self.config.max_sessions,
            rate_hz=self.config.rate_hz,
            budget_ms=m.budget_ms if self.config.rate_hz else 0.0,
            load_ms=self._room[0],
            free_worlds=self._room[1] if self.ready else 0,
            ready=self.ready,
        )
        self._reply(query, info)

    @_guarded
    def _on_open(self, query: zenoh.Query) -> None:
        try:
            request = decode(bytes(query.payload.to_bytes()) if query.payload else b"", OpenSession)
        except DecodeError as exc:
            return self._reply(query, Error(code=ErrorCode.BAD_REQUEST, message=str(exc)))
        self._reply(query, self._call("open", (request, None)))

    @_guarded
    def _on_close(self, query: zenoh.Query) -> None:
        try:
            request = decode(bytes(query.payload.to_bytes()) if query.payload else b"", CloseSession)
        except DecodeError as exc:
            return self._reply(query, Error(code=ErrorCode.BAD_REQUEST, message=str(exc)))
        self._reply(query, self._call("close", request))

    def _session_request(self, query: zenoh.Query) -> CloseSession | Error:
        """The session and token a status or pose query carries; the session is the key's."""
        try:
            request = decode(bytes(query.payload.to_bytes()) if query.payload else b"", CloseSession)
        except DecodeError as exc:
            return Error(code=ErrorCode.BAD_REQUEST, message=f"{exc} (the payload carries the session's token)")
        return request.model_copy(update={"session": self.keys.session_of(query.key_expr)})

    @_guarded
    def _on_pose(self, query: zenoh.Query) -> None:
        """The latest estimate of every open session the selector matches, one reply each. No token:
        the same estimates are published on the pose keys, so Zenoh's access control decides who
        reads them; the token guards what steers a session."""
        wanted = query.key_expr
        latest = dict(self._latest)  # the loop thread adds and drops sessions meanwhile
        if "*" not in str(wanted):  # one session, by its exact key
            session = self.keys.session_of(wanted)
            if session not in latest:
                opened = session in self.manager.sessions
                text = f"session '{session}': " + ("no estimate yet" if opened else "is not open")
                return self._reply(query, Error(code=ErrorCode.BAD_REQUEST, message=text))
        with query:
            for session, payload in latest.items():
                key = zenoh.KeyExpr(self.keys.pose(session))
                if wanted.intersects(key):
                    query.reply(key, payload, encoding=_ESTIMATE)

    @_guarded
    def _on_status(self, query: zenoh.Query) -> None:
        request = self._session_request(query)
        self._reply(query, request if isinstance(request, Error) else self._call("status", request))

    @_guarded
    def _on_robot_sample(self, sample: zenoh.Sample) -> None:
        kind = Keys.kind_of(sample.key_expr)
        if kind == "frame":
            self._on_frame(sample)
        elif kind == "observation":
            self._on_observation(sample)

    def _on_frame(self, sample: zenoh.Sample) -> None:
        received = time.perf_counter()
        session = self.keys.session_of(sample.key_expr)
        try:
            frame = decode(bytes(sample.payload.to_bytes()), RobotFrame)
        except DecodeError as exc:
            self._inbox.put(("bad_frame", (session, str(exc)), None))
            return
        if frame.session != session:
            self._inbox.put(
                (
                    "bad_frame",
                    (session, f"RobotFrame.session: '{frame.session}' sent on the key of session '{session}'"),
                    None,
                )
            )
            return
        self._inbox.put(("frame", (frame, received), None))

    def _on_observation(self, sample: zenoh.Sample) -> None:
        session = self.keys.session_of(sample.key_expr)
        try:
            observation = decode(bytes(sample.payload.to_bytes()), PoseObservation)
        except DecodeError as exc:
            self._inbox.put(("bad_frame", (session, str(exc)), None))
            return
        if observation.session != session:
            text = f"PoseObservation.session: '{observation.session}' sent on the key of session '{session}'"
            self._inbox.put(("bad_frame", (session, text), None))
            return
        self._inbox.put(("observation", observation, None))

    @_guarded
    def _on_service(self, sample: zenoh.Sample) -> None:
        name = Keys.service_of(sample.key_expr)
        if name != self.keys.service:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._others.discard(name)
            else:
                self._others.add(name)

    @_guarded
    def _on_robot(self, sample: zenoh.Sample) -> None:
        session = self.keys.session_of(sample.key_expr)
        gone = sample.kind == zenoh.SampleKind.DELETE
        self._inbox.put(("robot", (session, gone, time.monotonic()), None))

    # ------------------------------------------------------------------ the loop
    def _guarded_run(self) -> None:
        """The loop; should anything escape it, the service stops announcing itself (a live token
        on a dead loop would look healthy to robots and to the health check) and says so."""
        try:
            self._run()
        except BaseException:
            log.critical("the GPU loop died", exc_info=True)
            self._withdraw()

    def _watch(self) -> None:
        """A loop that stops coming round (stuck in a step or a build) is as dead as one that raised."""
        while not self._stop.wait(0.5) and not self.failed.is_set():
            stalled, limit = time.monotonic() - self._beat, self.config.watchdog_s
            if self.ready and stalled > limit:
                log.critical("the GPU loop has not come round for %.1f s (watchdog_s %g)", stalled, limit)
                self._withdraw()

    def _withdraw(self) -> None:
        """Stop announcing the service (token, ready) and tell `serve` to exit non-zero."""
        log.critical("withdrawing the service's liveliness token")
        self.ready = False
        token, self._token = self._token, None
        if token is not None:
            token.undeclare()
        self.failed.set()

    def _run(self) -> None:
        m, cfg = self.manager, self.config
        log.info("service '%s' warming up on %s: compiling kernels", cfg.name, self.device)
        m.warm()
        self._room = (m.load_ms(), m.free_worlds())
        self._beat = time.monotonic()
        self.ready = True
        self._token = self.session.liveliness().declare_token(self.keys.alive)  # only now do robots see us
        log.info("service '%s' ready on %s, device %s", cfg.name, ", ".join(cfg.listen) or "-", self.device)
        refreshed = resumed = time.monotonic()
        while not self._stop.is_set():
            self._beat = time.monotonic()
            idle = not any(s.pending for s in m.sessions.values())
            try:
                item = self._inbox.get(timeout=0.01 if idle else 0.0005)
            except queue.Empty:
                item = None
            while item is not None:
                self._handle(*item)
                try:
                    item = self._inbox.get_nowait()
                except queue.Empty:
                    item = None
            for pool in m.ready(cfg.max_wait_s):
                try:
                    estimates = m.step(pool)
                except Exception as exc:
                    # One population's failure (its physics or its tracker) is its sessions' error,
                    # not the service's: they are failed with the reason, the others go on.
                    sessions = m.fail(pool, f"{type(exc).__name__}: {exc}")
                    log.exception("tracking step failed for sessions %s; they are closed to frames", sessions)
                    continue
                for estimate in estimates:
                    payload = encode(estimate)
                    self._latest[estimate.session] = payload
                    pub = self._publishers.get(estimate.session)
                    if pub is not None:
                        pub.put(payload)  # the publisher's encoding: Estimate's
                    self._share(estimate)
            if self._view is not None:
                try:
                    self._view.update(m.sessions)
                except Exception:  # a view is not worth the service: log it and stop drawing
                    log.exception("the live view failed; it is closed")
                    self._view.close()
                    self._view = None
            now = time.monotonic()
            if now - self._beat > _STALL_S:
                # The service itself was busy (a first step compiling kernels on a cold cache can
                # take minutes on a CPU): its robots were waiting for an estimate, not silent.
                resumed = now
            for session, since in list(self._robot_gone.items()):
                if now - since > cfg.robot_timeout_s:
                    log.info("closing session %s: its robot's liveliness token is gone", session)
                    self._drop(session)
            for session in [s.id for s in m.sessions.values() if now - max(s.heard, resumed) > cfg.idle_timeout_s]:
                log.info("closing session %s: no frame for %.0f s", session, cfg.idle_timeout_s)
                self._drop(session)
            if now - refreshed > 0.2:  # what info answers: read here, where the populations change
                self._room, refreshed = (m.load_ms(), m.free_worlds()), now
        for session in list(m.sessions):
            self._drop(session)
        if m.frame_times.points:
            m.frame_times.save(cfg.frame_time_cache)

    def _handle(self, kind: str, payload, done: Future | None) -> None:
        m = self.manager
        self._in_flight = done
        try:
            if kind == "frame":
                frame, received = payload
                m.submit(frame, received)
                if self._recorder is not None:
                    self._recorder.frame(frame)
            elif kind == "observation":
                m.observe(payload)
                if self._recorder is not None:
                    self._recorder.observation(payload)
            elif kind == "bad_frame":
                m.count_error(*payload)
            elif kind == "robot":
                session, gone, when = payload
                if gone and session in m.sessions:
                    self._robot_gone[session] = when
                else:
                    self._robot_gone.pop(session, None)
            elif kind == "open":
                self._open(*payload, done)
            elif kind == "built":
                self._adopt(*payload)
            elif kind == "close":
                m.authorize(payload.session, payload.token)
                self._drop(payload.session)
                _answer(done, CloseSession(session=payload.session))
            elif kind == "status":
                _answer(done, m.status(payload.session, payload.token))
        except ServiceError as exc:
            _answer(done, exc.to_message(sorted(self._others) if exc.code == ErrorCode.CAPACITY else None))
        except Exception as exc:  # the loop never dies of a request; the caller gets the reason
            log.exception("request '%s' failed", kind)
            _answer(done, Error(code=ErrorCode.INTERNAL, message=f"{type(exc).__name__}: {exc}"))

    def _open(self, request: OpenSession, notice: str | None, done: Future | None) -> None:
        """Open in a population with room, or queue the open behind the build of its population
        on the builder thread, so that the running sessions keep stepping meanwhile."""
        m = self.manager
        admission = m.admit(request)
        admission.notice = admission.notice or notice
        if admission.pool is None:
            self._waiting.setdefault(admission.key, []).append((admission.request, done, admission.notice))
            if admission.key not in m.building:
                m.reserve(admission)
                robot, obj, worlds = admission.key[:3]
                log.info("building a population of %d x %d worlds (%s, %s)", self.config.groups, worlds, robot, obj)
                build = self._builder.submit(m.build, admission)
                began = time.monotonic()
                build.add_done_callback(lambda f: self._inbox.put(("built", (admission, f, began), None)))
            return
        info = m.attach(admission)
        # Gone until its robot's liveliness token shows up: a robot that never declares one
        # does not hold a session for ever.
        self._robot_gone[info.session] = time.monotonic()
        self._publishers[info.session] = self.session.declare_publisher(
            self.keys.pose(info.session),
            encoding=_ESTIMATE,
            express=True,
            priority=zenoh.Priority.REAL_TIME,
        )
        if self._ros is not None:
            self._ros.open(info.session, info.object)
        if self._recorder is not None:
            self._recorder.open(info, request)
        _answer(done, info)

    def _adopt(self, admission: Admission, build: Future, began: float) -> None:
        """A build finished: its population joins the loop and the opens that waited for it go on."""
        waiting = self._waiting.pop(admission.key, [])
        try:
            pool = build.result()
        except Exception as exc:
            self.manager.building.pop(admission.key, None)
            log.error("building a population for %s failed", admission.key[:3], exc_info=exc)
            for _, done, _ in waiting:
                _answer(done, Error(code=ErrorCode.INTERNAL, message=f"building its population failed: {exc!r}"))
            return
        self.manager.adopt(pool)
        log.info("population built in %.1f s", time.monotonic() - began)
        for request, done, notice in waiting:
            self._handle("open", (request, notice), done)

    def _drop(self, session: str) -> None:
        if session not in self.manager.sessions:
            return
        self.manager.drop(session)
        self._robot_gone.pop(session, None)
        self._latest.pop(session, None)
        pub = self._publishers.pop(session, None)
        if pub is not None:
            pub.undeclare()
        if self._ros is not None:
            self._ros.drop(session)
        if self._recorder is not None:
            self._recorder.close(session)

    def _share(self, estimate) -> None:
        """An estimate to ROS 2 and the recording. Their failure is logged and theirs alone: the
        robot's own estimate went out already."""
        try:
            if self._ros is not None:
                self._ros.publish(estimate)
            if self._recorder is not None:
                self._recorder.estimate(estimate)
        except Exception:
            log.exception("publishing session %s's estimate to ROS 2 or its recording failed", estimate.session)


def _answer(done: Future | None, value) -> None:
    """Answer a request once: a stopping service may have answered it already."""
    if done is not None:
        with contextlib.suppress(InvalidStateError):
            done.set_result(value)
