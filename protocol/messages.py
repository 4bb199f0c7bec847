"""Every message of the protocol, as typed pydantic models over the generic codec.

Arrays are numpy arrays (float32 unless stated) validated for rank and finiteness here, at the
boundary; sizes that depend on the session (D joints, L sensors) are checked by the service
against the session it opened.
"""

from __future__ import annotations

import base64
import math
import re
from enum import StrEnum
from typing import Annotated, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    Field,
    StrictInt,
    create_model,
    field_validator,
)

from .arrays import Matrix6, Pose, Vector, array_field
from .base import WireMessage
from .sensing import SENSING

__all__ = [
    "AUTO",
    "DEFAULT_METHOD",
    "DEFAULT_WORLDS",
    "METHODS",
    "PROTOCOL_VERSION",
    "SESSION_NAME",
    "CloseSession",
    "Error",
    "ErrorCode",
    "OpenSession",
    "PoseObservation",
    "RobotFrame",
    "ServiceInfo",
    "SessionInfo",
    "check_version",
]

PROTOCOL_VERSION = 7
"""Bumped, with the key prefix's ``v7``, whenever a message gains or changes a field."""
DEFAULT_WORLDS = 40
"""K, the paper's: a session's worlds where no frame budget decides (``worlds="auto"`` on a
service without one, benchmarks)."""
AUTO = "auto"
"""``OpenSession.worlds``: the most worlds the service's frame budget allows now."""
METHODS = ("OLP", "EYE", "WRS", "REPS", "PBO")
"""The optimizers a session may ask for: open loop, the paper's EYE baseline, and its three optimizers."""
DEFAULT_METHOD = "PBO"
"""A session's optimizer when it does not say."""
_NAME_PATTERN = r"^[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$"


def _ros_name(name: str) -> str:
    # A validator, not a pattern: pydantic's pattern error shows users a regular expression.
    if not re.fullmatch(_NAME_PATTERN, name):
        raise ValueError(
            f"'{name}' is not a ROS 2 name: letters, digits and _, each part starting with a letter,"
            " parts joined by / (as in lab2/left_hand)"
        )
    return name


SESSION_NAME = Annotated[
    str, AfterValidator(_ros_name), Field(max_length=127, json_schema_extra={"pattern": _NAME_PATTERN})
]
"""A session's name: ROS 2 name tokens, joined by ``/`` into a namespace."""


REACH = 10.0
"""How far from the robot's world origin a pose may lie [m]: a hand's workspace, with room to spare."""


def _within_reach(pose: np.ndarray) -> np.ndarray:
    distance = float(np.linalg.norm(pose[:3].astype(np.float64)))
    if distance > REACH:
        raise ValueError(f"position {pose[:3].tolist()} lies {distance:.3g} m from the origin, beyond {REACH:g} m")
    return pose


class ErrorCode(StrEnum):
    BAD_REQUEST = "bad_request"
    VERSION_MISMATCH = "version_mismatch"
    UNKNOWN_ROBOT = "unknown_robot"
    UNKNOWN_OBJECT = "unknown_object"
    CAPACITY = "capacity"
    FORBIDDEN = "forbidden"
    INTERNAL = "internal"


class Error(WireMessage):
    code: Annotated[ErrorCode, Field(strict=False)]  # the wire carries its value, a string
    """What kind of refusal (:class:`ErrorCode`)."""
    message: str
    """What was wrong, naming the field and the numbers."""
    others: list[str] = Field(default_factory=list)
    """On ``capacity``: other services on the same Zenoh network that may have room."""


def check_version(version: int) -> None:
    """Raise a ValueError naming both versions when ``version`` is not this protocol's."""
    if version != PROTOCOL_VERSION:
        raise ValueError(f"protocol version mismatch: client speaks v{version}, service speaks v{PROTOCOL_VERSION}")


class ServiceInfo(WireMessage):
    """What the service's info queryable answers."""

    protocol: int = PROTOCOL_VERSION
    """The service's protocol version."""
    name: str
    """The service's name: its keys live under ``inhand/v7/{name}``."""
    device: str
    """Where its simulations run (``cuda:0``, ``cpu``)."""
    robots: list[str]
    """The robots a session may open with."""
    objects: list[str]
    """The objects a session may track."""
    methods: list[str]
    """The optimizers a session may choose."""
    groups: int
    """Sessions per population."""
    max_worlds: int
    """Worlds the service may hold in all."""
    sessions: int
    """Sessions open now."""
    max_sessions: int
    """Sessions open at once at most."""
    rate_hz: float
    """The frame rate the service keeps up with [Hz]; 0: no frame budget."""
    budget_ms: float
    """The frame budget: the p99 time all populations' steps together may take [ms]."""
    load_ms: float
    """The p99 step time of the populations open or being built now, summed [ms]."""
    free_worlds: int
    """The most worlds (K) a session opened now in a new population would get; 0 when the service
    is full."""
    ready: bool = True
    """False while the service compiles its kernels on start; opens wait until it is ready."""
    building: int = 0
    """Populations being built now: an open that needs one is answered when it is built."""
    build_s: float = 0.0
    """How long the service's last population build took [s] (0: none yet): what an open that
    needs a build waits."""
    key: str = ""
    """The service's public key (base64: Ed25519's 32 bytes, then X25519's 32; protocol.identity):
    a robot configured with it, or with its fingerprint, knows the service by it."""
    stamp: float = 0.0
    """The service's clock when it said this [s, Unix time]: a beat older than the last is a replay."""
    signature: str = ""
    """The service's Ed25519 signature of this info with ``signature`` empty."""


class OpenSession(WireMessage):
    """Ask the service to track one object in one robot's hand."""

    protocol: int = PROTOCOL_VERSION
    """The client's protocol version: a service of another refuses the open with ``version_mismatch``."""
    robot: str
    """One of ``ServiceInfo.robots``."""
    object: str
    """One of ``ServiceInfo.objects``."""
    p0: Pose
    """Initial object pose estimate: position [m], quaternion (x, y, z, w)."""
    sigma_t: float = Field(0.005, ge=0.0, le=0.1)
    """Translation noise of p0 [m] (Sigma_p)."""
    sigma_r: float = Field(0.1, ge=0.0, le=3.2)
    """Rotation noise of p0 [rad] (Sigma_p)."""
    q0: Vector | None = None
    """Joint positions at the start, (D,); default the robot's start pose."""
    method: str = DEFAULT_METHOD
    """The optimizer: OLP, EYE, WRS, REPS or PBO."""
    worlds: Annotated[StrictInt, Field(ge=1, le=65536)] | Literal["auto"] = AUTO
    """K, the session's worlds; "auto": the most the service's frame budget allows now."""
    allow_fewer: bool = False
    """Take fewer worlds than asked for when the budget has no room for them, instead of a refusal."""
    overrides: dict[str, float] = Field(default_factory=dict)
    """Tracker settings by their dotted names (e.g. update_every, exploration.wrench_force,
    optimizer.min_separation); a flag as 1 or 0."""
    name: SESSION_NAME | None = None
    """The session's name, ROS name tokens joined by ``/`` (a namespace, as in ``lab2/left_hand``):
    its ROS 2 topics and TF frame are named after it (``/inhand/{name}/pose``, ``{name}``), so a
    launch file or an RViz config can name them. A name another open session holds is refused.
    Default: ``{peer}/{robot}_{object}`` for an open under a peer name, else ``{robot}_{object}``.
    A second unnamed session of the same default is refused on a service that publishes ROS 2
    topics (so that a topic's name never hangs on which robot opened first), else numbered from 2."""
    client_key: str = ""
    """The robot's X25519 public key (base64), made for this open or kept by the robot: the
    session's secret is agreed from it and the service's key, and the reply carries no token
    (protocol.identity). An open with a key must carry its :attr:`proof`."""
    stamp: float = 0.0
    """The service's clock when the robot sent the open, reckoned from the service's info
    (``ServiceInfo.stamp``) [s]: a proven open more than 30 s off it is refused, so a recorded
    open cannot be replayed later."""
    proof: str = ""
    """HMAC-SHA256 (base64) of the open's other fields under a key agreed from :attr:`client_key`
    and the service's key (protocol.identity): the sender holds the private half of the key it
    names, so the service counts its caps, names and kept room by that key."""

    @field_validator("client_key")
    @classmethod
    def _x25519_key(cls, key: str) -> str:
        try:
            raw = base64.b64decode(key, validate=True)
        except ValueError:
            raw = None
        if key and (raw is None or len(raw) != 32):
            size = "not base64" if raw is None else f"{len(raw)} bytes"
            raise ValueError(f"expected an X25519 public key, 32 bytes in base64, got {size}")
        return key

    @field_validator("p0")
    @classmethod
    def _unit_quaternion(cls, p0: np.ndarray) -> np.ndarray:
        # The service normalises the quaternion: one of zero, denormal or overflowing length has
        # no direction to keep.
        norm = float(np.linalg.norm(p0[3:].astype(np.float64)))
        if not 1e-3 <= norm <= 1e3:
            raise ValueError(f"quaternion (x, y, z, w) = {p0[3:].tolist()} has length {norm:.3g}, expected about 1")
        return _within_reach(p0)

    @field_validator("overrides")
    @classmethod
    def _finite(cls, overrides: dict[str, float]) -> dict[str, float]:
        bad = {k: v for k, v in overrides.items() if not math.isfinite(v)}
        if bad:
            raise ValueError(f"non-finite values {bad}")
        return overrides


class CloseSession(WireMessage):
    """Close a session; also the payload of a session's status query. Only its robot may close or
    query it: the request carries ``mac`` and ``stamp`` (protocol.auth.signed_query), or the token."""

    session: str
    """The session's id (:attr:`SessionInfo.session`)."""
    token: str = ""
    """The session's secret from :class:`SessionInfo`; a robot that signs (``mac``) leaves it empty,
    so that a peer answering in the service's place learns nothing."""
    stamp: float = Field(0.0, allow_inf_nan=False)
    """When the robot sent the request [s, Unix time], for ``mac``."""
    mac: str = ""
    """HMAC-SHA256 of the request's purpose, session and stamp, keyed by the token (protocol.auth)."""


class SessionInfo(WireMessage):
    """The service's answer to OpenSession."""

    protocol: int = PROTOCOL_VERSION
    """The service's protocol version."""
    session: str
    """The session's id: its keys are ``inhand/v7/{service}/s/{session}/...``."""
    token: str
    """The session's secret: every frame, close, status and pose query must carry it. Zenoh's
    access control (or mTLS) decides who may connect and read; the token keeps peers that may
    from steering or closing another robot's session."""
    robot: str
    """The session's robot."""
    object: str
    """The session's object."""
    joint_names: list[str]
    """The robot's joints in the order of every (D,) array: ``q``, ``controls``, ``q0``."""
    sensor_names: list[str]
    """The robot's fingertip sensors in the order of every (L, ...) array: ``force``, ``slip``, ..."""
    zone_names: list[str] = Field(default=[])  # pydantic copies it per model; the schema shows it
    """The robot's touch zones in the order of the (Z,) ``touch`` array; empty when it has none."""
    worlds: int
    """K, the worlds granted."""
    method: str
    """The session's optimizer."""
    notice: str | None = None
    """Why the session got fewer worlds than it asked for, when it did."""
    name: str = ""
    """The session's name (:attr:`OpenSession.name`): its ROS 2 topics and TF frame follow it."""
    signature: str = ""
    """For an open with a ``client_key``: the service's Ed25519 signature of this reply (with
    ``signature`` empty) followed by that key, so that it answers that open alone."""


class _FrameHeader(WireMessage):
    session: str
    """The session this frame belongs to (also in its key)."""
    seq: int = Field(ge=0)
    """Frame counter, consecutive from 0; the service applies frames in seq order."""
    epoch: int = Field(0, ge=0)
    """How often the robot restarted its seq counter in this session. A signed frame of a newer
    epoch re-synchronises the session to its seq; one of an older epoch, or of the same epoch and
    behind what was applied, is never applied: a relay that replays recorded frames steers nothing."""
    stamp: float = Field(ge=0.0, le=1e10, allow_inf_nan=False)
    """Robot clock when the frame was sensed [s]: 0 to 1e10 (seconds since boot, or since 1970)."""
    token: str = ""
    """The session's secret (:attr:`SessionInfo.token`), from a robot that does not sign; one that
    signs (``mac``) leaves it empty, so that the token never travels after the open."""
    mac: str = ""
    """HMAC-SHA256 of this frame with ``token`` and ``mac`` empty, keyed by the token (protocol.auth):
    a frame carries it or the token, else it is refused."""


def _sensing_fields() -> dict:
    fields = {}
    for f in SENSING:
        kind = array_field(1 + len(f.trailing), f.trailing[-1] if f.trailing else None)
        text = f"{f.doc} Shape {({'joint': 'D', 'sensor': 'L', 'zone': 'Z'}[f.per], *f.trailing)} [{f.unit}]."
        fields[f.name] = (kind | None, Field(None, description=text)) if f.optional else (kind, Field(description=text))
    return fields


RobotFrame = create_model(
    "RobotFrame",
    __base__=_FrameHeader,
    __doc__="What the robot sends every control frame: the header and the fields of protocol.SENSING.",
    **_sensing_fields(),
)


class PoseObservation(WireMessage):
    """The object's pose as another sensor saw it (a camera's pose estimator: FoundationPose,
    PoseRBPF), sent at any rate on the session's ``observation`` key. The tracker scores its worlds
    against it, and re-seeds them around it when none agrees with a confident one."""

    session: str
    token: str = ""
    """The session's secret (:attr:`SessionInfo.token`), from a robot that does not sign (``mac``)."""
    mac: str = ""
    """HMAC-SHA256 of this observation with ``token`` and ``mac`` empty, keyed by the token (protocol.auth)."""
    stamp: float = Field(ge=0.0, le=1e10, allow_inf_nan=False)
    """Robot clock when the sensor saw the pose [s]: an observation more than the service's
    ``max_observation_age_s`` older than the newest frame is counted stale and dropped."""
    pose: Pose
    """The observed pose in the robot's world frame, (7,): position [m], unit quaternion (x, y, z, w)."""
    covariance: Matrix6
    """Its uncertainty, (6, 6): position [m^2] and rotation vector [rad^2] about ``pose``, world
    frame; symmetric positive-definite."""

    @field_validator("pose")
    @classmethod
    def _unit_quaternion(cls, pose: np.ndarray) -> np.ndarray:
        norm = float(np.linalg.norm(pose[3:].astype(np.float64)))
        if abs(norm - 1.0) > 1e-2:
            raise ValueError(f"quaternion (x, y, z, w) = {pose[3:].tolist()} has length {norm:.4g}, expected 1 +- 0.01")
        return _within_reach(pose)

    @field_validator("covariance")
    @classmethod
    def _positive_definite(cls, cov: np.ndarray) -> np.ndarray:
        c = cov.astype(np.float64)
        asymmetry = float(np.abs(c - c.T).max())
        if asymmetry > 1e-6 * max(float(np.abs(c).max()), 1e-12):
            raise ValueError(f"expected a symmetric matrix, largest |C - C^T| = {asymmetry:.3g}")
        smallest = float(np.linalg.eigvalsh(c).min())
        if smallest <= 0:
            raise ValueError(f"expected positive-definite, smallest eigenvalue {smallest:.3g}")
        return cov
