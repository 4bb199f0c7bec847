"""Proof that a message comes from a session's robot, without its secret on the wire.

The open's reply (seen by the robot alone: a query's reply goes to the querier) carries the
session's token. After that the token never travels: a frame or an observation carries ``mac``, an
HMAC-SHA256 of its own encoding (with ``token`` and ``mac`` empty) keyed by the token; a status or
close query carries a ``stamp`` and the HMAC of its purpose, session and stamp. A peer that reads
every frame or catches every query learns nothing that steers the session. The standard library's
hmac does this; nothing here is cryptography of our own.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import time

from pydantic import BaseModel

from .codec import encode

__all__ = ["QUERY_WINDOW_S", "mac_of", "query_mac", "sign", "signed_query", "verify", "verify_query"]

QUERY_WINDOW_S = 300.0
"""How far a query's stamp may lie from the service's clock [s]: robot and service clocks need
only agree to minutes (NTP does far better)."""


def _mac(token: str, data: bytes) -> str:
    return hmac.new(token.encode(), data, hashlib.sha256).hexdigest()[:32]


def sign(message: BaseModel, token: str) -> BaseModel:
    """``message`` (a frame or an observation) with its ``mac`` set and its ``token`` empty."""
    bare = message.model_copy(update={"token": "", "mac": ""})
    return bare.model_copy(update={"mac": _mac(token, encode(bare))})


def verify(message: BaseModel, token: str) -> bool:
    """Whether ``message`` comes from the holder of ``token``: by its ``mac``, or (robots that do
    not sign) by the token itself."""
    if message.mac:
        bare = message.model_copy(update={"token": "", "mac": ""})
        return secrets.compare_digest(message.mac, _mac(token, encode(bare)))
    return bool(message.token) and secrets.compare_digest(message.token, token)


def mac_of(message: BaseModel, token: str) -> str:
    """The HMAC of ``message`` (an estimate) with its ``mac`` empty, keyed by ``token``."""
    return _mac(token, encode(message.model_copy(update={"mac": ""})))


def query_mac(token: str, purpose: str, session: str, stamp: float) -> str:
    """The MAC of a ``purpose`` ("status", "close") query about ``session`` sent at ``stamp`` [s, Unix time]."""
    return _mac(token, f"{purpose}:{session}:{stamp!r}".encode())


def signed_query(request: BaseModel, token: str, purpose: str) -> BaseModel:
    """A status or close request (:class:`protocol.CloseSession`) stamped now and signed for ``purpose``."""
    stamp = time.time()
    return request.model_copy(
        update={"token": "", "stamp": stamp, "mac": query_mac(token, purpose, request.session, stamp)}
    )


def verify_query(request: BaseModel, token: str, purpose: str, now: float | None = None) -> bool:
    """Whether a status or close request comes from the holder of ``token``: a ``purpose`` MAC
    stamped within :data:`QUERY_WINDOW_S` of ``now``, or (robots that do not sign) the token."""
    if request.mac:
        fresh = abs((time.time() if now is None else now) - request.stamp) <= QUERY_WINDOW_S
        expected = query_mac(token, purpose, request.session, request.stamp)
        return fresh and secrets.compare_digest(request.mac, expected)
    return bool(request.token) and secrets.compare_digest(request.token, token)
