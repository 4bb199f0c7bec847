"""How the client's Zenoh session is configured and how its messages are labelled on the wire."""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Iterable

import zenoh

from inhand_tracker.protocol import encoding_of

__all__ = ["check_endpoints", "connected", "zenoh_config", "zenoh_encoding"]

_ENDPOINT = re.compile(r"(tcp|udp|tls|quic|ws|unixsock-stream|unixpipe|serial|vsock)/[^\s/#?][^\s]*")
"""A Zenoh locator: a transport, then its address (``tcp/127.0.0.1:7447``), optionally ``#`` options."""


def check_endpoints(endpoints: Iterable[str], what: str) -> list[str]:
    """``endpoints`` as given; a ValueError in one line naming the first that is no Zenoh endpoint
    (Zenoh itself answers ``127.0.0.1:7447`` with a long traceback, and only once it opens)."""
    out = list(endpoints)
    for e in out:
        if not _ENDPOINT.fullmatch(e):
            hint = f"tcp/{e}" if re.fullmatch(r"[\w.\-\[\]:]+:\d+", e) else "tcp/HOST:PORT"
            raise ValueError(f"{what}: '{e}' is not a Zenoh endpoint; write it as {hint}")
    return out


def connected(session: zenoh.Session) -> bool:
    """Whether the session reaches a router or a peer now."""
    return bool(list(session.info.routers_zid()) or list(session.info.peers_zid()))


@functools.cache
def zenoh_encoding(model: type) -> zenoh.Encoding:
    """The Zenoh encoding of a message: msgpack, with the message's name and version as schema."""
    return zenoh.Encoding(encoding_of(model))


def zenoh_config(
    listen=(), connect=(), scouting: bool = False, file: str | os.PathLike | None = None, mode: str | None = None
) -> zenoh.Config:
    """A Zenoh config: listen and connect endpoints, multicast scouting on or off, ``mode`` ("peer",
    or "client" behind a router that relays nothing between peers, as rmw_zenoh's); on top of the
    Zenoh config ``file`` when given (TLS certificates, access control rules), whose mode stands
    where ``mode`` is None (peer where neither says)."""
    listen, connect = check_endpoints(listen, "listen"), check_endpoints(connect, "connect")
    conf = zenoh.Config.from_file(str(file)) if file else zenoh.Config()
    if mode is not None:
        conf.insert_json5("mode", f'"{mode}"')
    elif conf.get_json("mode") == "null":
        conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "true" if scouting else "false")
    if connect:
        conf.insert_json5("connect/endpoints", str(list(connect)).replace("'", '"'))
    if listen:
        conf.insert_json5("listen/endpoints", str(list(listen)).replace("'", '"'))
    return conf
