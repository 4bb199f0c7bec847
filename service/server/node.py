"""The service on Zenoh: handlers that only decode, validate and queue, one loop thread that
owns the GPU (the :class:`SessionManager`) and publishes every estimate, and a builder thread
that builds new populations between the loop's steps, so that an open never freezes the others.

Keys (protocol/keys.py): a liveliness token ``alive``; queryables ``info``, ``rpc/open/**``,
``rpc/close``, ``s/*/pose`` (latest estimate) and ``s/*/status``; one subscriber on ``s/*/*`` for
the robots' frames and observations, in arrival order; a liveliness subscriber on ``s/*/robot``
that closes a session whose robot is gone past the timeout."""

from __future__ import annotations

import functools
import logging
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor

import zenoh

from inhand_tracker.client.zenoh_session import connected, zenoh_config, zenoh_encoding
from inhand_tracker.protocol import (
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
    decode,
    encode,
)
from inhand_tracker.protocol.identity import ServiceKey, signed
from inhand_tracker.service.paths import resolve
from inhand_tracker.service.tracker import METHODS, changed
from inhand_tracker.sim_backend import load_catalog, load_robot, resolve_device

from .admission import Admission, ServiceError
from .config import ServiceConfig
from .inbox import Inbox, Request, answer, guarded, reply
from .outputs import Outputs
from .pools import PoolKey
from .recording import SessionRecorder
from .ros2 import RosTopics, ros_namespace
from .ros2_input import ROS_PEER, RosHost, RosInputs, check_sessions
from .sessions import SessionManager

__all__ = ["TrackerNode"]

log = logging.getLogger(__name__)

_ESTIMATE = zenoh_encoding(Estimate)
_ROBOT_MESSAGES = {"frame": RobotFrame, "observation": PoseObservation}
"""What a robot publishes on its session's keys, by the key's last chunk."""
_STALL_S = 1.0
"""A turn of the service's loop longer than this [s] was the service's own stall: the sessions'
idle time counts again from its end."""


class TrackerNode:
    """The long-running tracking service of one process."""

    def __init__(self, config: ServiceConfig):
        self.keys = Keys(config.name)
        robots = {spec.name: spec for spec in (load_robot(resolve(path)) for path in config.robots)}
        catalog = load_catalog(resolve(config.objects))
        check_sessions(config.ros2_sessions, robots, catalog)
        self.device = str(resolve_device(config.device))
        self.manager = SessionManager(config, robots, catalog, ServiceKey.load_or_create(config.key_file))
        self.config = config = self.manager.config  # groups resolved for the device
        self._inbox = Inbox()
        self._latest: dict[str, bytes] = {}
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._robot_gone: dict[str, float] = {}
        self._stop = threading.Event()
        self.failed = threading.Event()
        """Set when the loop thread died: the service withdrew its liveliness token and must exit."""
        self._loop = threading.Thread(target=self._guarded_run, name="inhand-gpu-loop", daemon=True)
        self.ready = False
        """Kernels compiled and the liveliness token declared: sessions may open."""
        self._beat = time.monotonic()  # when the loop last came round [s, monotonic]
        self._builder = ThreadPoolExecutor(max_workers=1, thread_name_prefix="inhand-build")  # off the loop
        self._waiting: dict[PoolKey, list[tuple[Admission, Future | None]]] = {}  # opens awaiting a build
        self._build_s = 0.0  # how long the last population build took [s]
        self._token = None
        self.session: zenoh.Session | None = None
        self._others: set[str] = set()
        """The other services on this network (their tokens): named to a robot this one has no room for."""
        self._linked = True  # a peer or router of ``connect`` reached at the last look (said when it changes)
        self._room = (0.0, 0)  # the loop's latest (load_ms, free_worlds), for the info queryable
        self.outputs = Outputs()
        """ROS 2 topics (setting ``ros2``), recordings (``record``) and the live view (``view_port``)."""
        if config.record:
            self.outputs.add(SessionRecorder(config.record, config.name, config.ros2_frame_id, said=self._say))

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> TrackerNode:
        cfg, keys = self.config, self.keys
        file = resolve(cfg.zenoh_config) if cfg.zenoh_config else None
        self.session = s = zenoh.open(zenoh_config(cfg.listen, cfg.connect, cfg.scouting, file, cfg.zenoh_mode))
        self._entities = [
            s.declare_queryable(keys.info, self._on_info),
            s.declare_queryable(keys.opens, self._on_open),
            s.declare_queryable(keys.close, self._on_close),
            s.declare_queryable(keys.every("pose"), self._on_pose),
            s.declare_queryable(keys.every("status"), self._on_status),
            # One subscriber for frames and observations (zenoh-python runs each on a thread of its own:
            # two would let a frame overtake an observation); remote only: these keys carry estimates too.
            s.declare_subscriber(keys.every("*"), self._on_robot_sample, allowed_origin=zenoh.Locality.REMOTE),
            s.liveliness().declare_subscriber(keys.every("robot"), self._on_robot, history=True),
            s.liveliness().declare_subscriber(Keys.services("alive"), self._on_service, history=True),
        ]
        if cfg.ros2:
            self.outputs.add(RosTopics(s, cfg.ros2_domain, cfg.ros2_frame_id, cfg.ros2_tf, ros_namespace(cfg.name)))
        if cfg.ros2_sessions:
            host = RosHost(self._inbox.post, self._open, self._frame, self._observation)
            self.outputs.add(RosInputs(s, cfg.ros2_domain, cfg.ros2_sessions, host, ros_namespace(cfg.name)))
        if cfg.view_port:
            from .viewer import LiveView  # viser, only where a view is asked for

            self.outputs.add(LiveView(cfg.view_host, cfg.view_port))
        self._loop.start()  # it warms up, then declares the service's liveliness token
        self._watchdog = threading.Thread(target=self._watch, name="inhand-watchdog", daemon=True)
        self._watchdog.start()
        return self

    def close(self) -> None:
        """Stop the loop, close every session, leave Zenoh."""
        self._stop.set()
        if self._loop.is_alive():
            self._loop.join(timeout=10)
        # Zenoh's close waits for handlers that wait on a busy or dead loop: answer them, so it can go.
        self._builder.shutdown(wait=False, cancel_futures=True)
        self._inbox.cancel((done for waits in self._waiting.values() for _, done in waits), "the service is stopping")
        self.outputs.close()
        if self.session is not None:
            self.session.close()
            self.session = None

    def __enter__(self) -> TrackerNode:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ zenoh handlers (decode, queue)
    @guarded
    def _on_info(self, query: zenoh.Query) -> None:
        reply(query, self._info())

    def _info(self) -> ServiceInfo:
        """What the service says of itself, signed by its key: the info queryable's answer and the beat."""
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
            building=len(m.building),
            build_s=self._build_s,
            key=m.identity.public,
            stamp=time.time(),
        )
        return signed(m.identity, info)

    @guarded
    def _on_open(self, query: zenoh.Query) -> None:
        if (peer := self.keys.peer_of(str(query.key_expr))) is None:
            return  # a wildcard selector that reaches rpc/open/** (a watcher's inhand/**/pose) is no open
        try:
            request = decode(bytes(query.payload.to_bytes()) if query.payload else b"", OpenSession)
        except DecodeError as exc:
            return reply(query, Error(code=ErrorCode.BAD_REQUEST, message=str(exc)))
        reply(query, self._inbox.call("open", functools.partial(self._open, request, None, peer)))

    @guarded
    def _on_close(self, query: zenoh.Query) -> None:
        try:
            request = decode(bytes(query.payload.to_bytes()) if query.payload else b"", CloseSession)
        except DecodeError as exc:
            return reply(query, Error(code=ErrorCode.BAD_REQUEST, message=str(exc)))
        reply(query, self._inbox.call("close", lambda _: self._close(request)))

    def _session_request(self, query: zenoh.Query) -> CloseSession | Error:
        """The session and token a status or pose query carries; the session is the key's."""
        try:
            request = decode(bytes(query.payload.to_bytes()) if query.payload else b"", CloseSession)
        except DecodeError as exc:
            return Error(code=ErrorCode.BAD_REQUEST, message=f"{exc} (the payload carries the session's token)")
        return request.model_copy(update={"session": self.keys.session_of(query.key_expr)})

    @guarded
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
                return reply(query, Error(code=ErrorCode.BAD_REQUEST, message=text))
        with query:
            for session, payload in latest.items():
                key = zenoh.KeyExpr(self.keys.pose(session))
                if wanted.intersects(key):
                    query.reply(key, payload, encoding=_ESTIMATE)

    @guarded
    def _on_status(self, query: zenoh.Query) -> None:
        request = self._session_request(query)
        if isinstance(request, Error):
            return reply(query, request)
        status = lambda _: self.manager.status_of(self.manager.authorize_query(request, "status"))  # noqa: E731
        reply(query, self._inbox.call("status", status))

    @guarded
    def _on_robot_sample(self, sample: zenoh.Sample) -> None:
        """A frame or an observation: decoded and checked against its key here, applied on the loop."""
        received = time.perf_counter()
        kind = Keys.kind_of(sample.key_expr)
        message_type = _ROBOT_MESSAGES.get(kind)
        if message_type is None:
            return
        session = self.keys.session_of(sample.key_expr)
        try:
            message = decode(bytes(sample.payload.to_bytes()), message_type)
        except DecodeError as exc:
            text = str(exc)
            return self._inbox.post("bad input", lambda _: self.manager.count_error(session, text))
        if message.session != session:
            text = f"{message_type.__name__}.session: '{message.session}' sent on the key of session '{session}'"
            return self._inbox.post("bad input", lambda _: self.manager.count_error(session, text))
        if kind == "frame":
            self._inbox.post("frame", lambda _: self._frame(message, received))
        else:
            self._inbox.post("observation", lambda _: self._observation(message))

    @guarded
    def _on_service(self, sample: zenoh.Sample) -> None:
        name = Keys.service_of(sample.key_expr)
        if name != self.keys.service:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._others.discard(name)
            else:
                self._others.add(name)

    @guarded
    def _on_robot(self, sample: zenoh.Sample) -> None:
        session = self.keys.session_of(sample.key_expr)
        gone, when = sample.kind == zenoh.SampleKind.DELETE, time.monotonic()
        self._inbox.post("robot", lambda _: self._robot_seen(session, gone, when))

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
        """A loop that stops coming round (stuck in a step or a build) is as dead as one that raised;
        a router that does not answer (not started, the wrong address) is said, and again when it does."""
        while not self._stop.wait(0.5) and not self.failed.is_set():
            if self.config.connect and (linked := connected(self.session)) != self._linked:
                self._linked, where = linked, ", ".join(self.config.connect)
                (log.info if linked else log.warning)("Zenoh: %s %s", "reached" if linked else "no answer at", where)
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
        self.outputs.warm(m)  # the live view's kernels too: not when the first browser connects
        self._room, self._beat = (m.load_ms(), m.free_worlds()), time.monotonic()
        self.ready = True
        self._token = self.session.liveliness().declare_token(self.keys.alive)  # only now do robots see us
        log.info("service '%s' ready on %s, device %s, key %s", cfg.name, ", ".join(cfg.listen) or "-", self.device,
                 m.identity.fingerprint)  # fmt: skip
        refreshed = resumed = time.monotonic()
        while not self._stop.is_set():
            self._beat = time.monotonic()
            idle = not any(s.pending for s in m.sessions.values())
            request = self._inbox.next(0.01 if idle else 0.0005)
            while request is not None:
                self._inbox.handle(request, self._refusal)
                request = self._inbox.next(0)
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
                    self.outputs.estimate(estimate)  # after the robot's own: an output's failure is its own
            self.outputs.tick(m.sessions)
            now = time.monotonic()
            if now - self._beat > _STALL_S:
                # The service itself was busy (a first step compiling kernels on a cold cache can
                # take minutes on a CPU): its robots were waiting for an estimate, not silent.
                resumed = now
            for session, since in list(self._robot_gone.items()):
                if now - since > cfg.robot_timeout_s:
                    self._drop(session, "its robot's liveliness token is gone")
            for session in [s.id for s in m.sessions.values() if now - max(s.heard, resumed) > cfg.idle_timeout_s]:
                self._drop(session, f"no frame for {cfg.idle_timeout_s:.0f} s")
            if now - refreshed > 0.2:  # what info answers: read here, where the populations change
                self._room, refreshed = (m.load_ms(), m.free_worlds()), now
                self.session.put(self.keys.beat, encode(self._info()))  # what a keyed robot knows us alive by
        for session in list(m.sessions):
            self._drop(session, "the service is stopping")
        if m.frame_times.points:
            m.frame_times.save(cfg.frame_time_cache)

    def _say(self, session: str, message: str) -> None:
        """Tell a session's robot (its status and next estimate) what went wrong beside its tracking."""
        if (s := self.manager.sessions.get(session)) is not None:
            s.last_error = s.notice = message

    def _refusal(self, exc: ServiceError) -> Error:
        """A refused request's answer; one refused for capacity names the other services there are."""
        return exc.to_message(sorted(self._others) if exc.code == ErrorCode.CAPACITY else None)

    # ------------------------------------------------------------------ requests, on the loop thread
    def _frame(self, frame: RobotFrame, received: float) -> None:
        self.manager.submit(frame, received)
        self.outputs.frame(frame)

    def _observation(self, observation: PoseObservation) -> None:
        self.manager.observe(observation)
        self.outputs.observation(observation)

    def _robot_seen(self, session: str, gone: bool, when: float) -> None:
        """A robot's liveliness token came or went: a session whose robot is gone past the timeout closes."""
        if gone and session in self.manager.sessions:
            self._robot_gone[session] = when
        else:
            self._robot_gone.pop(session, None)

    def _close(self, request: CloseSession) -> CloseSession:
        self.manager.authorize_query(request, "close")
        self._drop(request.session)
        return CloseSession(session=request.session)

    def _open(self, request: OpenSession, notice: str | None, peer: str, done: Future | None) -> SessionInfo | None:
        """Open in a population with room, or queue the open behind the build of its population
        on the builder thread, so that the running sessions keep stepping meanwhile."""
        m = self.manager
        admission = m.admit(request, peer)
        admission.notice = admission.notice or notice
        if admission.pool is None:
            if admission.key not in m.building:  # the first open of a population builds it
                m.gate.build_for(admission.source)  # or is refused, before it waits for anything
                m.reserve(admission)
                robot, obj, worlds = admission.key.robot, admission.key.object, admission.key.worlds
                log.info("building a population of %d x %d worlds (%s, %s)", self.config.groups, worlds, robot, obj)
                began, build = time.monotonic(), self._builder.submit(m.build, admission)
                build.add_done_callback(lambda f: self._inbox.post("built", lambda _: self._adopt(admission, f, began)))
            self._waiting.setdefault(admission.key, []).append((admission, done))
            return None
        info = m.attach(admission)
        # Gone until its robot's liveliness token shows up: a robot that never declares one does not
        # hold a session for ever. A ROS 2 robot declares none: its frames hold it (idle timeout).
        if not peer.startswith(ROS_PEER):
            self._robot_gone[info.session] = time.monotonic()
        self._publishers[info.session] = self.session.declare_publisher(
            self.keys.pose(info.session),
            encoding=_ESTIMATE,
            express=True,
            priority=zenoh.Priority.REAL_TIME,
        )
        self.outputs.open(info, request)
        log.info(  # the settings beyond the defaults: its robot config's and its overrides
            "session %s opened: robot '%s', object '%s', %d worlds, %s%s%s", info.session, info.robot, info.object,
            info.worlds, info.method, f", settings {c}" if (c := changed(admission.tracker_config)) else "",
            f" ({info.notice})" if info.notice else "",
        )  # fmt: skip
        return info

    def _adopt(self, admission: Admission, build: Future, began: float) -> None:
        """A build finished: its population joins the loop and the opens that waited for it go on."""
        waiting = self._waiting.pop(admission.key, [])
        try:
            pool = build.result()
        except Exception as exc:
            self.manager.building.pop(admission.key, None)
            log.error("building a population for %s failed", admission.key, exc_info=exc)
            for _, done in waiting:
                answer(done, Error(code=ErrorCode.INTERNAL, message=f"building its population failed: {exc!r}"))
            return
        self.manager.adopt(pool)
        self._build_s = time.monotonic() - began
        log.info("population built in %.1f s", self._build_s)
        for waited, done in waiting:
            # The robot is told why its open took as long: on a fresh GPU machine, minutes.
            built = f"its population was built for it: {self._build_s:.0f} s"
            notice = "; ".join(filter(None, (waited.notice, built)))
            opening = functools.partial(self._open, waited.request, notice, waited.peer)
            self._inbox.handle(Request("open", opening, done), self._refusal)

    def _drop(self, session: str, why: str = "its robot closed it") -> None:
        s = self.manager.sessions.get(session)
        if s is None:
            return
        log.info("session %s closed (%s): %d frames, %d errors", session, why, s.frames, s.errors)
        self.manager.drop(session)
        self._robot_gone.pop(session, None)
        self._latest.pop(session, None)
        pub = self._publishers.pop(session, None)
        if pub is not None:
            pub.undeclare()
        self.outputs.drop(session)
