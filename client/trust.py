"""What a client checks of its service when it knows the service's key (``serve`` prints its
fingerprint): its info and open replies carry the service's signature, the session's secret is
agreed rather than sent, and every estimate carries a MAC under that secret (protocol.identity).
A client with a key of its own (``identity``) proves it in each open, so the service knows the
robot again by it: its caps, its names and the room the service keeps for its robots."""

from __future__ import annotations

import logging
import os
import secrets
import time

import zenoh

from inhand_tracker.protocol import DecodeError, ErrorCode, Estimate, OpenSession, ServiceInfo, SessionInfo, decode
from inhand_tracker.protocol.auth import mac_of
from inhand_tracker.protocol.identity import RobotKey, matches, verified

from .errors import TrackerError

__all__ = ["Trust"]

log = logging.getLogger(__name__)

SILENT_S = 2.0
"""A service whose signed beat (five a second) has not come for this long is gone [s]."""


class Trust:
    """The checks of one client; each passes everything when no key is configured (with a warning
    that says what that means)."""

    def __init__(self, service_key: str | None, identity: str | os.PathLike | None = None):
        self.service_key = service_key
        self.identity = None if identity is None else RobotKey.load_or_create(identity)
        """The robot's own key, kept in the file ``identity`` (None: a key per open, with the service's key)."""
        self._exchange: RobotKey | None = None
        self._public = ""
        self._clock = (0.0, 0.0)  # the last info's stamp [s, the service's clock] and when it came [s, monotonic]
        self.forged = 0
        """Estimates refused: their MAC was not the service's."""
        self._warned = False
        self._stamp, self._heard = 0.0, time.monotonic()
        self._beats = None

    def info(self, info: ServiceInfo) -> ServiceInfo:
        """``info``, when it is the configured service's; else a TrackerError (forbidden)."""
        if self.service_key is not None and not (matches(self.service_key, info.key) and verified(info.key, info)):
            raise TrackerError(
                ErrorCode.FORBIDDEN,
                f"service '{info.name}' does not hold the key {self.service_key} (its key: {info.key or 'none'}):"
                " not the service this client was configured for",
            )
        self._clock = (info.stamp, time.monotonic())
        return info

    def request(self, request: OpenSession, info: ServiceInfo) -> OpenSession:
        """The open, with the robot's key (or one of this open's own when the service's key is
        known) and its proof (``info`` is checked first: a client that chose among services may have
        heard any peer)."""
        if self.service_key is None and not self._warned:
            self._warned = True
            log.warning(
                "no service_key given: any peer on this Zenoh network could answer as the service (the open,"
                " the estimates); give the fingerprint `inhand-tracker serve` prints"
            )
        if self.service_key is None and self.identity is None:
            return request
        self._exchange, self._public = self.identity or RobotKey(), self.info(info).key
        stamp, heard = self._clock
        stamp = (stamp + time.monotonic() - heard) if stamp == info.stamp else info.stamp
        return self._exchange.prove(info.key, request.model_copy(update={"client_key": self._exchange.public,
                                                                        "stamp": stamp}))  # fmt: skip

    def opened(self, reply: SessionInfo) -> SessionInfo:
        """The open's reply, with the session's secret agreed in it; a TrackerError (forbidden) when
        the reply is not the service's answer to this open."""
        if self._exchange is None:
            return reply
        if not verified(self._public, reply, self._exchange.public):
            raise TrackerError(ErrorCode.FORBIDDEN, f"the reply to the open of session '{reply.session}' is not signed"
                               " by the service's key: something else answered the open")  # fmt: skip
        return reply.model_copy(update={"token": self._exchange.secret(self._public, reply.session)})

    def watch(self, session: zenoh.Session, key: str) -> None:
        """Know the service alive by its signed beats on ``key`` (after a keyed open): a liveliness
        token is anyone's to hold, a beat only the service's to sign, and an old one is not newer."""
        if self._beats is not None:  # a reopen's: the last service's beats are no longer this session's
            self._beats.undeclare()
            self._beats = None
        if self._exchange is not None:
            # A reopened session's service may be another process, on another clock: its beats
            # are compared with each other only.
            self._stamp, self._heard = 0.0, time.monotonic()
            self._beats = session.declare_subscriber(key, self._on_beat)

    def _on_beat(self, sample: zenoh.Sample) -> None:
        try:
            info = decode(bytes(sample.payload.to_bytes()), ServiceInfo)
        except DecodeError:
            return
        if info.stamp > self._stamp and info.key == self._public and verified(self._public, info):
            self._stamp, self._heard = info.stamp, time.monotonic()

    def alive(self) -> bool:
        """Whether the service's beat was heard within :data:`SILENT_S` (always, without a key)."""
        return self._beats is None or time.monotonic() - self._heard < SILENT_S

    def checked(self, estimate: Estimate, token: str) -> Estimate:
        """``estimate``, when it is the service's; else a TrackerError (forbidden)."""
        if not self.estimate(estimate, token):
            raise TrackerError(ErrorCode.FORBIDDEN, f"estimate {estimate.seq}: not the service's (its MAC)")
        return estimate

    def estimate(self, estimate: Estimate, token: str) -> bool:
        """Whether ``estimate`` is the service's (always, without a key); a forged one is counted."""
        if self._exchange is None or secrets.compare_digest(estimate.mac, mac_of(estimate, token)):
            return True
        self.forged += 1
        return False
