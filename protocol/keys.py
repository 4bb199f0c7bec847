"""Every Zenoh key expression of the protocol, in one place.

``inhand/v7/{service}/...``: the version is the protocol's; it changes when a message changes
incompatibly.
"""

from __future__ import annotations

import re

from .messages import PROTOCOL_VERSION

__all__ = ["PREFIX", "Keys", "check_name", "session_id"]

PREFIX = f"inhand/v{PROTOCOL_VERSION}"
_NAME = re.compile(r"^[A-Za-z0-9_\-.]{1,64}$")
_SESSION = re.compile(r"^([A-Za-z0-9_\-.]{1,64}~)?[A-Za-z0-9_\-.]{1,64}$")


def check_name(kind: str, name: str) -> str:
    """A service, peer or session name usable as one key chunk (no '/', '*', '$', '#', '?' or
    blanks; a session's may carry its peer's name and '~' first)."""
    if not isinstance(name, str) or not (_SESSION if kind == "session" else _NAME).match(name):
        raise ValueError(f"{kind} name: expected 1-64 characters of [A-Za-z0-9_-.], got {name!r}")
    return name


def session_id(peer: str, unique: str) -> str:
    """A new session's id: its robot's peer name (when it opened under one), '~' and ``unique``,
    so that a router's access rules can confine each robot to its own sessions' keys
    (``inhand/*/*/s/PEER~$*/frame``)."""
    return f"{peer}~{unique}" if _NAME.match(peer) else unique


class Keys:
    """The key expressions of one service."""

    def __init__(self, service: str = "default", peer: str | None = None):
        self.service = check_name("service", service)
        self.root = f"{PREFIX}/{self.service}"
        self.peer = None if peer is None else check_name("peer", peer)
        """The name a robot opens under (``rpc/open/PEER``), or None: the service counts its caps
        per name, and a router's access rules can let each certificate open under its own name only."""

    @property
    def alive(self) -> str:
        """Liveliness token of the service."""
        return f"{self.root}/alive"

    @property
    def beat(self) -> str:
        """The service publishes its signed info here five times a second: a robot that knows the
        service's key knows it alive by it (a liveliness token can be held by anyone)."""
        return f"{self.root}/beat"

    @property
    def info(self) -> str:
        """Queryable: version, device, robots, objects, capacity."""
        return f"{self.root}/info"

    @property
    def open(self) -> str:
        """Queryable with payload: open a session (under :attr:`peer`'s name when it has one)."""
        return f"{self.root}/rpc/open" + (f"/{self.peer}" if self.peer else "")

    @property
    def opens(self) -> str:
        """The service's open queryable: an open under any name, or none."""
        return f"{self.root}/rpc/open/**"

    def peer_of(self, key: str) -> str | None:
        """The name an open on ``key`` was made under ("" for none); None for a key that is not
        one open's (a wildcard selector that the open queryable also matches, or a name
        :func:`check_name` refuses, such as one of several chunks)."""
        head = f"{self.root}/rpc/open"
        if key == head:
            return ""
        peer = key[len(head) + 1 :] if key.startswith(head + "/") else ""
        return peer if peer and _NAME.fullmatch(peer) else None

    @property
    def close(self) -> str:
        """Queryable with payload: close a session."""
        return f"{self.root}/rpc/close"

    def frame(self, session: str) -> str:
        """Subscriber: the robot's frames, in seq order."""
        return f"{self.root}/s/{check_name('session', session)}/frame"

    def pose(self, session: str) -> str:
        """Publisher of every estimate, and a queryable answering the latest."""
        return f"{self.root}/s/{check_name('session', session)}/pose"

    def observation(self, session: str) -> str:
        """Subscriber: pose observations of the session's object (vision), at any rate."""
        return f"{self.root}/s/{check_name('session', session)}/observation"

    def status(self, session: str) -> str:
        """Queryable: counters, latency, health."""
        return f"{self.root}/s/{check_name('session', session)}/status"

    def robot(self, session: str) -> str:
        """Liveliness token of the session's robot."""
        return f"{self.root}/s/{check_name('session', session)}/robot"

    def every(self, kind: str) -> str:
        """The wildcard over all sessions' ``kind`` keys (frame, observation, pose, status, robot),
        or over all their keys (``*``)."""
        if kind not in ("frame", "observation", "pose", "status", "robot", "*"):
            raise ValueError(f"key kind: expected frame, observation, pose, status, robot or *, got {kind!r}")
        return f"{self.root}/s/*/{kind}"

    @staticmethod
    def kind_of(key: str) -> str:
        """The last chunk of a per-session key: frame, observation, pose, status or robot."""
        return str(key).rsplit("/", 1)[-1]

    @staticmethod
    def services(kind: str) -> str:
        """The wildcard over every service's ``alive`` token or ``info`` queryable."""
        if kind not in ("alive", "info"):
            raise ValueError(f"key kind: expected alive or info, got {kind!r}")
        return f"{PREFIX}/*/{kind}"

    @staticmethod
    def service_of(key: str) -> str:
        """The service chunk of any key of the protocol."""
        parts = str(key).split("/")
        if len(parts) < 3 or "/".join(parts[:2]) != PREFIX:
            raise ValueError(f"key {key!r} is not under {PREFIX}")
        return parts[2]

    def session_of(self, key: str) -> str:
        """The session chunk of a per-session key of this service."""
        head = f"{self.root}/s/"
        if not str(key).startswith(head):
            raise ValueError(f"key {key!r} is not a session key of service '{self.service}'")
        return str(key)[len(head) :].split("/", 1)[0]
