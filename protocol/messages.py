"""Every message of the protocol, as typed pydantic models over the generic codec.

Arrays are numpy arrays (float32 unless stated) validated for rank and finiteness here, at the
boundary; sizes that depend on the session (D joints, L sensors) are checked by the service
against the session it opened.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Annotated

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, PlainSerializer

__all__ = [
    "PROTOCOL_VERSION",
    "CloseSession",
    "Error",
    "ErrorCode",
    "Estimate",
    "OpenSession",
    "RobotFrame",
    "ServiceInfo",
    "SessionInfo",
    "Status",
    "check_version",
]

PROTOCOL_VERSION = 1
"""Bumped with the key prefix's ``v1`` when a message changes incompatibly."""


def _array(rank: int, last: int | None = None):
    def convert(value):
        arr = np.asarray(value, dtype=np.float32)
        if arr.ndim != rank:
            raise ValueError(f"expected {rank} dimensions, got shape {arr.shape}")
        if last is not None and arr.shape[-1] != last:
            raise ValueError(f"expected last dimension {last}, got shape {arr.shape}")
        bad = ~np.isfinite(arr)
        if bad.any():
            index = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValueError(f"{int(bad.sum())} non-finite values, first at {index} = {arr[index]}")
        return arr

    return Annotated[np.ndarray, BeforeValidator(convert), PlainSerializer(lambda a: a, return_type=np.ndarray)]


Vector = _array(1)
Pose = _array(1, 7)
Vec3s = _array(2, 3)
Vec2s = _array(2, 2)
Matrix6 = _array(2, 6)


class _Message(BaseModel):
    model_config = ConfigDict(arbitrary_types_allowed=True, frozen=True, extra="forbid")


class ErrorCode(StrEnum):
    BAD_REQUEST = "bad_request"
    VERSION_MISMATCH = "version_mismatch"
    UNKNOWN_ROBOT = "unknown_robot"
    UNKNOWN_OBJECT = "unknown_object"
    UNKNOWN_SESSION = "unknown_session"
    CAPACITY = "capacity"
    INTERNAL = "internal"


class Error(_Message):
    code: ErrorCode
    message: str


def check_version(version: int) -> None:
    """Raise a ValueError naming both versions when ``version`` is not this protocol's."""
    if version != PROTOCOL_VERSION:
        raise ValueError(f"protocol version mismatch: client speaks v{version}, service speaks v{PROTOCOL_VERSION}")


class ServiceInfo(_Message):
    """What the service's info queryable answers."""

    protocol: int = PROTOCOL_VERSION
    name: str
    device: str
    robots: list[str]
    objects: list[str]
    methods: list[str]
    groups: int
    """Sessions per population."""
    max_worlds: int
    sessions: int
    """Sessions open now."""


class OpenSession(_Message):
    """Ask the service to track one object in one robot's hand."""

    protocol: int = PROTOCOL_VERSION
    robot: str
    object: str
    p0: Pose
    """Initial object pose estimate: position [m], quaternion (x, y, z, w)."""
    sigma_t: float = Field(0.005, ge=0.0, le=0.1)
    """Translation noise of p0 [m] (Sigma_p)."""
    sigma_r: float = Field(0.1, ge=0.0, le=3.2)
    """Rotation noise of p0 [rad] (Sigma_p)."""
    q0: Vector | None = None
    """Joint positions at the start, (D,); default the robot's start pose."""
    method: str = "PBO"
    worlds: int = Field(40, ge=1, le=65536)
    overrides: dict[str, float] = Field(default_factory=dict)
    """Tracker hyperparameters by name (e.g. update_every, wrench_force)."""


class CloseSession(_Message):
    session: str


class SessionInfo(_Message):
    """The service's answer to OpenSession."""

    protocol: int = PROTOCOL_VERSION
    session: str
    robot: str
    object: str
    joint_names: list[str]
    sensor_names: list[str]
    worlds: int
    method: str


class RobotFrame(_Message):
    """What the robot sends every control frame."""

    session: str
    seq: int = Field(ge=0)
    stamp: float
    """Robot clock [s]."""
    controls: Vector
    """Joint position targets, (D,) [rad or m]."""
    q: Vector
    """Measured joint positions, (D,) [rad or m]."""
    force: Vec3s | None = None
    """Fingertip forces in the sensor frames, (L, 3) [N]."""
    slip: Vector | None = None
    """Translational slip flags, (L,)."""
    slip_dir: Vec2s | None = None
    """Slip directions in the sensors' tangent planes, (L, 2)."""
    spin: Vector | None = None
    """Rotational slip flags, (L,)."""
    spin_sense: Vector | None = None
    """Rotational slip senses, (L,): 1 counter-clockwise about the pad normal, else 0."""


class Estimate(_Message):
    """The tracker's answer to one frame."""

    session: str
    seq: int
    stamp: float
    pose: Pose
    mean_pose: Pose
    covariance: Matrix6
    """Covariance of (position [m], rotation vector [rad]) about the mean pose, (6, 6)."""
    cost: float
    mass: float
    friction: float
    status: str
    latency_ms: float


class Status(_Message):
    session: str
    frames: int
    gaps: int
    duplicates: int
    late: int
    errors: int
    latency_p50_ms: float
    latency_p99_ms: float
    cost: float
    spread_m: float
    last_error: str | None = None
