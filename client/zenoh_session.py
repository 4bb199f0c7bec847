"""How the client's Zenoh session is configured and how its messages are labelled on the wire."""

from __future__ import annotations

import functools
import os

import zenoh

from inhand_tracker.protocol import encoding_of

__all__ = ["zenoh_config", "zenoh_encoding"]


@functools.cache
def zenoh_encoding(model: type) -> zenoh.Encoding:
    """The Zenoh encoding of a message: msgpack, with the message's name and version as schema."""
    return zenoh.Encoding(encoding_of(model))


def zenoh_config(listen=(), connect=(), scouting: bool = False, file: str | os.PathLike | None = None) -> zenoh.Config:
    """A peer config: listen and connect endpoints, multicast scouting on or off; on top of the
    Zenoh config ``file`` when given (TLS certificates, access control rules, ``mode: "client"``
    behind a router)."""
    conf = zenoh.Config.from_file(str(file)) if file else zenoh.Config()
    if conf.get_json("mode") == "null":
        conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "true" if scouting else "false")
    if connect:
        conf.insert_json5("connect/endpoints", str(list(connect)).replace("'", '"'))
    if listen:
        conf.insert_json5("listen/endpoints", str(list(listen)).replace("'", '"'))
    return conf
