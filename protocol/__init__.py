"""The wire protocol: typed messages, a msgpack codec (no pickle), every key expression,
and the trajectory file format.

Imports only numpy, msgpack and pydantic, so the robot-side client stays light.
"""

from .codec import MAX_ARRAY_BYTES, MAX_PAYLOAD_BYTES, DecodeError, decode, encode
from .keys import PREFIX, Keys, check_name
from .messages import (
    AUTO,
    DEFAULT_METHOD,
    DEFAULT_WORLDS,
    PROTOCOL_VERSION,
    CloseSession,
    Error,
    ErrorCode,
    Estimate,
    OpenSession,
    PoseObservation,
    RobotFrame,
    ServiceInfo,
    SessionInfo,
    SessionStatus,
    TrackState,
    check_version,
)
from .sensing import PRESENCE, SENSING, SensingAttributes, SensingField, check_sensing, sensing_field
from .trajectory import TRAJECTORY_FORMAT, TRAJECTORY_VERSION, GroundTruth, Trajectory

__all__ = [
    "AUTO",
    "DEFAULT_METHOD",
    "DEFAULT_WORLDS",
    "MAX_ARRAY_BYTES",
    "MAX_PAYLOAD_BYTES",
    "PREFIX",
    "PRESENCE",
    "PROTOCOL_VERSION",
    "SENSING",
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
    "PoseObservation",
    "RobotFrame",
    "SensingAttributes",
    "SensingField",
    "ServiceInfo",
    "SessionInfo",
    "SessionStatus",
    "TrackState",
    "Trajectory",
    "check_name",
    "check_sensing",
    "check_version",
    "decode",
    "encode",
    "sensing_field",
]
