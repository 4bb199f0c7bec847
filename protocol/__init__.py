"""The wire protocol: typed messages, a msgpack codec (no pickle), every key expression,
the trajectory file format and session recordings (MCAP).

Imports only numpy, msgpack and pydantic (and mcap and rosbags, to read a recording), so the
robot-side client stays light.
"""

from .codec import MAX_ARRAY_BYTES, MAX_PAYLOAD_BYTES, MEDIA_TYPE, DecodeError, checked, decode, encode, encoding_of
from .keys import PREFIX, Keys, check_name
from .messages import (
    AUTO,
    DEFAULT_METHOD,
    DEFAULT_WORLDS,
    METHODS,
    PROTOCOL_VERSION,
    SESSION_NAME,
    CloseSession,
    Error,
    ErrorCode,
    OpenSession,
    PoseObservation,
    RobotFrame,
    ServiceInfo,
    SessionInfo,
    check_version,
)
from .recording import CHANNELS, SessionRecording
from .reports import Estimate, PopulationSummary, SessionStatus, TrackState
from .sensing import PRESENCE, SENSING, SensingAttributes, SensingField, check_sensing, sensing_field
from .trajectory import TRAJECTORY_FORMAT, TRAJECTORY_VERSION, GroundTruth, Trajectory

__all__ = [
    "AUTO",
    "CHANNELS",
    "DEFAULT_METHOD",
    "DEFAULT_WORLDS",
    "MAX_ARRAY_BYTES",
    "MAX_PAYLOAD_BYTES",
    "MEDIA_TYPE",
    "METHODS",
    "PREFIX",
    "PRESENCE",
    "PROTOCOL_VERSION",
    "SENSING",
    "SESSION_NAME",
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
    "PopulationSummary",
    "PoseObservation",
    "RobotFrame",
    "SensingAttributes",
    "SensingField",
    "ServiceInfo",
    "SessionInfo",
    "SessionRecording",
    "SessionStatus",
    "TrackState",
    "Trajectory",
    "check_name",
    "check_sensing",
    "check_version",
    "checked",
    "decode",
    "encode",
    "encoding_of",
    "sensing_field",
]
