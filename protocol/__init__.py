"""The wire protocol: typed messages, a msgpack codec (no pickle), every key expression,
and the trajectory file format.

Imports only numpy, msgpack and pydantic, so the robot-side client stays light.
"""

from .codec import MAX_ARRAY_BYTES, MAX_PAYLOAD_BYTES, DecodeError, decode, encode
from .keys import PREFIX, Keys, check_name
from .messages import (
    PROTOCOL_VERSION,
    CloseSession,
    Error,
    ErrorCode,
    Estimate,
    OpenSession,
    RobotFrame,
    ServiceInfo,
    SessionInfo,
    Status,
    check_version,
)
from .trajectory import TRAJECTORY_FORMAT, TRAJECTORY_VERSION, GroundTruth, Trajectory

__all__ = [
    "MAX_ARRAY_BYTES",
    "MAX_PAYLOAD_BYTES",
    "PREFIX",
    "PROTOCOL_VERSION",
    "TRAJECTORY_FORMAT",
    "TRAJECTORY_VERSION",
    "CloseSession",
    "DecodeError",
    "Error",
    "ErrorCode",
    "Estimate",
    "GroundTruth",
    "Keys",
    "OpenSession",
    "RobotFrame",
    "ServiceInfo",
    "SessionInfo",
    "Status",
    "Trajectory",
    "check_name",
    "check_version",
    "decode",
    "encode",
]
