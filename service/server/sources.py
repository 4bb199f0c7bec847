"""Who opens: an open's source (the robot key its open proves, or none), the names bound to keys,
and whom the service keeps room for.

On a plain Zenoh network any peer can open under any name and make as many keys as it likes, so
the service cannot tell a robot from a stranger by what an open says; it can tell a robot that
proves a key it was told of. So: caps count per key (a stranger's flood spends its own); a peer name
or session name that a key holds is that key's while its session lives and for ``reopen_window_s``
after (from the start, for the names in ``robot_keys``); and the last ``reserved_sessions`` sessions
and ``reserved_populations`` populations are kept for the robots in ``robot_keys``, so that no flood
of strangers, however many keys it makes, refuses their opens or their reopens.
"""

from __future__ import annotations

import math
import time

from inhand_tracker.protocol import ErrorCode, OpenSession
from inhand_tracker.protocol.identity import ServiceKey, fingerprint

from .admission import ServiceError
from .config import ServiceConfig
from .pools import Source

__all__ = ["OPEN_WINDOW_S", "Sources"]

OPEN_WINDOW_S = 30.0
"""A proven open whose stamp is further than this from the service's clock is refused [s]."""
_REPLAY = "proof: this open was sent before (a replay); open anew"


class Sources:
    """The proofs seen, and the names held by keys."""

    def __init__(self, config: ServiceConfig, identity: ServiceKey):
        self.config, self.identity = config, identity
        self._proofs: dict[str, tuple[float, bool]] = {}
        """Proofs of recent opens: until when they are remembered [s, monotonic], and whether their
        session was opened (an open waiting for a build is admitted twice, a replay never)."""
        self._held: dict[tuple[str, str], tuple[str, float]] = {
            ("peer", name): (key, math.inf) for name, key in config.robot_keys.items()
        }
        """(``peer`` or ``name``, the name) -> the key fingerprint holding it, and until when [s,
        monotonic; inf while its session lives, and for the listed robots' names]."""

    def source(self, request: OpenSession, peer: str) -> Source:
        """Who sent ``request`` under ``peer``'s name ("" for none); a ServiceError (forbidden)
        when it names a key it does not prove, is stale or seen before, or asks for a name another
        key holds."""
        now, key = time.monotonic(), ""
        if request.client_key:
            key = self._proven(request, now)
        for kind, name in (("peer", peer), ("name", request.name or "")):
            holder, until = self._held.get((kind, name), ("", 0.0))
            if name and holder and holder != key and until > now:
                said = f"{kind}: '{name}' is held by robot key {holder}"
                listed = kind == "peer" and name in self.config.robot_keys
                why = "the robot_keys setting names it" if listed else "its session"
                raise ServiceError(ErrorCode.FORBIDDEN, f"{said} ({why}); open under a name of your own")
        known = bool(key) and key in self.config.robot_keys.values()
        return Source(key, known, f"robot key {key}" if key else (f"peer '{peer}'" if peer else ""))

    def _proven(self, request: OpenSession, now: float) -> str:
        try:
            proven = self.identity.proven(request)
        except ValueError:
            proven = False
        if not proven:
            raise ServiceError(
                ErrorCode.FORBIDDEN, "proof: the open does not prove its client_key (made with another key, or none)"
            )
        drift = request.stamp - time.time()
        if abs(drift) > OPEN_WINDOW_S:
            raise ServiceError(
                ErrorCode.FORBIDDEN,
                f"stamp: {request.stamp:.3f} s is {drift:+.1f} s from this service's clock, the most is"
                f" {OPEN_WINDOW_S:g} s (an old open replayed, or a stamp not from the service's info)",
            )
        for proof in [p for p, (until, _) in self._proofs.items() if until < now]:
            del self._proofs[proof]
        until, opened = self._proofs.get(request.proof, (now + 2 * OPEN_WINDOW_S, False))
        if opened:
            raise ServiceError(ErrorCode.FORBIDDEN, _REPLAY)
        self._proofs[request.proof] = until, False
        return fingerprint(request.client_key)

    def held(self, key: str) -> set[str]:
        """The session names that keys other than ``key`` hold now."""
        now = time.monotonic()
        return {n for (kind, n), (k, until) in self._held.items() if kind == "name" and k != key and until > now}

    def spend(self, request: OpenSession) -> None:
        """Spend an open's proof as its session opens: a replay admitted while the open it copies
        waited for a build is refused here."""
        if request.proof in self._proofs:
            until, opened = self._proofs[request.proof]
            if opened:
                raise ServiceError(ErrorCode.FORBIDDEN, _REPLAY)
            self._proofs[request.proof] = until, True

    def bind(self, source: Source, peer: str, name: str) -> None:
        """A session of ``source`` opened: its peer name and name are its key's while it lives."""
        for held in (("peer", peer), ("name", name)):
            if source.key and held[1]:
                self._held[held] = source.key, math.inf

    def closed(self, key: str, peer: str, name: str, peer_open: bool) -> None:
        """A session of robot key ``key`` ended: its names stay its key's for ``reopen_window_s``
        (its peer name as long as another of its sessions lives, ``peer_open``)."""
        if not key:
            return
        until = time.monotonic() + self.config.reopen_window_s
        if peer not in self.config.robot_keys and not peer_open and peer:
            self._held["peer", peer] = key, until
        self._held["name", name] = key, until
        now = time.monotonic()
        for held in [h for h, (_, t) in self._held.items() if t < now]:
            del self._held[held]
