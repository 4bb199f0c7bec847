"""Every message of the protocol, as typed pydantic models over the generic codec.

Arrays are numpy arrays (float32 unless stated) validated for rank and finiteness here, at the
boundary; sizes that depend on the session (D joints, L sensors) are checked by the service
against the session it opened.
"""

from __future__ import annotations

import math
from enum import IntEnum, StrEnum
from typing import Annotated, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictInt,
    create_model,
    field_validator,
)

from .arrays import Matrix6, Pose, Poses, Vector, array_field
from .sensing import SENSING

__all__ = [
    "AUTO",
    "DEFAULT_METHOD",
    "DEFAULT_WORLDS",
    "METHODS",
    "PROTOCOL_VERSION",
    "CloseSession",
    "Error",
    "ErrorCode",
    "Estimate",
    "OpenSession",
    "PopulationSummary",
    "PoseObservation",
    "RobotFrame",
    "ServiceInfo",
    "SessionInfo",
    "SessionStatus",
    "TrackState",
    "check_version",
]

PROTOCOL_VERSION = 4
"""Bumped, with the key prefix's ``v4``, when a message changes incompatibly."""
DEFAULT_WORLDS = 40
"""K, the paper's: a session's worlds where no frame budget decides (``worlds="auto"`` on a
service without one, benchmarks)."""
AUTO = "auto"
"""``OpenSession.worlds``: the most worlds the service's frame budget allows now."""
METHODS = ("OLP", "EYE", "WRS", "REPS", "PBO")
"""The optimizers a session may ask for: open loop, the paper's EYE baseline, and its three optimizers."""
DEFAULT_METHOD = "PBO"
"""A session's optimizer when it does not say."""


REACH = 10.0
"""How far from the robot's world origin a pose may lie [m]: a hand's workspace, with room to spare."""


def _within_reach(pose: np.ndarray) -> np.ndarray:
    distance = float(np.linalg.norm(pose[:3].astype(np.float64)))
    if distance > REACH:
        raise ValueError(f"position {pose[:3].tolist()} lies {distance:.3g} m from the origin, beyond {REACH:g} m")
    return pose


class _Message(BaseModel):
    # Field docstrings become the JSON Schema's descriptions (docs/protocol). Strict: a wire value
    # of the wrong type ("3" for a protocol version, "yes" for a flag) is refused, not coerced.
    model_config = ConfigDict(
        arbitrary_types_allowed=True, frozen=True, extra="forbid", use_attribute_docstrings=True, strict=True
    )


class ErrorCode(StrEnum):
    BAD_REQUEST = "bad_request"
    VERSION_MISMATCH = "version_mismatch"
    UNKNOWN_ROBOT = "unknown_robot"
    UNKNOWN_OBJECT = "unknown_object"
    CAPACITY = "capacity"
    FORBIDDEN = "forbidden"
    INTERNAL = "internal"


class Error(_Message):
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


class ServiceInfo(_Message):
    """What the service's info queryable answers."""

    protocol: int = PROTOCOL_VERSION
    """The service's protocol version."""
    name: str
    """The service's name: its keys live under ``inhand/v4/{name}``."""
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


class OpenSession(_Message):
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
    name: str | None = Field(None, pattern=r"^[A-Za-z][A-Za-z0-9_]{0,62}$")
    """The session's name, a ROS name token: its ROS 2 topics and TF frame are named after it
    (``/inhand/{name}/pose``, ``{name}``), so a launch file or an RViz config can name them. A name
    another open session holds is refused. Default ``{robot}_{object}``, numbered from 2 when taken."""

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


class CloseSession(_Message):
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


class SessionInfo(_Message):
    """The service's answer to OpenSession."""

    protocol: int = PROTOCOL_VERSION
    """The service's protocol version."""
    session: str
    """The session's id: its keys are ``inhand/v4/{service}/s/{session}/...``."""
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
    zone_names: list[str] = []
    """The robot's touch zones in the order of the (Z,) ``touch`` array; empty when it has none."""
    worlds: int
    """K, the worlds granted."""
    method: str
    """The session's optimizer."""
    notice: str | None = None
    """Why the session got fewer worlds than it asked for, when it did."""
    name: str = ""
    """The session's name (:attr:`OpenSession.name`): its ROS 2 topics and TF frame follow it."""


class _FrameHeader(_Message):
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


class PoseObservation(_Message):
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


class TrackState(IntEnum):
    """How far an estimate is to be trusted; :attr:`Estimate.status` carries its lower-case name."""

    TRACKING = 0
    """The worlds agree with the robot and with each other."""
    UNCERTAIN = 1
    """The object's surface points spread across the cost-weighted worlds (position and rotation
    together) more than the tracker's ``uncertain_spread``."""
    DIVERGED = 2
    """The worlds lost the object, or the best world and the real hand disagree about contact: the
    hypotheses were re-seeded this frame around the last trusted estimate."""
    RECOVERING = 3
    """Re-seeded recently; not trusted until ``recover_frames`` have passed."""
    AMBIGUOUS = 4
    """The worlds that agree with the robot fall into two pose modes (``Estimate.modes``) that
    contact cannot tell apart, e.g. a brick turned end for end: the estimate may be either."""


class Estimate(_Message):
    """The tracker's answer to one frame. Poses are in the robot's world frame (the frame of the
    robot config's base), position [m] and unit quaternion (x, y, z, w)."""

    session: str
    """The session this estimate belongs to."""
    seq: int
    """The seq of the frame this estimate answers."""
    stamp: float
    """That frame's robot clock [s]."""
    pose: Pose
    """The estimate of the object's pose, (7,): by default the cost-weighted mean over the worlds of
    the lowest-cost world's mode (``modes``), which is ``mean_pose`` wherever the worlds agree, else
    the lowest-cost world's (setting ``mean_estimate``)."""
    mean_pose: Pose
    """The cost-weighted mean object pose over the session's worlds, (7,)."""
    covariance: Matrix6
    """Cost-weighted covariance of (position [m^2], rotation vector [rad^2], world frame) about
    ``mean_pose``, (6, 6), plus what that spread cannot show: the model's mismatch (a floor that
    grows with ``cost``) and how coarsely the worlds sample the start region: the truth should lie
    in its 95 % region on about 95 % of frames."""
    cost: float
    """The best world's mean cost since the last optimizer update (eq. 3, dimensionless)."""
    mass: float
    """The best world's object mass [kg]."""
    friction: float
    """The best world's object friction coefficient (dimensionless)."""
    status: str
    """A :class:`TrackState` name in lower case: tracking, uncertain, diverged, recovering or ambiguous."""
    modes: Poses | None = None
    """The two heaviest pose modes of the worlds, (2, 7): the lowest-cost world's pose, then the
    heaviest world's away from it (within 0.5 rad and 2 cm of it is the same mode)."""
    mode_weights: Vector | None = None
    """The share of the cost weights in each mode, (2,): ambiguous when the second's is 0.25 or more."""
    evidence: float = 1.0
    """How strongly the session's last update moved its worlds' poses: 0, the sensing told them
    apart no better than its noise (or by their physics alone) and the worlds run open loop, to 1,
    full strength (always 1 unless the session's ``optimizer.by_evidence`` is on)."""
    latency_ms: float
    """From the frame's arrival at the service to this estimate [ms]."""
    notice: str | None = None
    """What the robot should know about this frame, once: e.g. that its seq jumped and the
    session re-synchronised to it."""


class PopulationSummary(_Message):
    """The session's worlds after a frame, as a recording keeps them: what the estimate rests on."""

    seq: int
    """The seq of the frame."""
    stamp: float
    """That frame's robot clock [s]."""
    worlds: int
    """K, the session's worlds."""
    cost: float
    """The best world's window cost (dimensionless)."""
    spread_m: float
    """RMS position spread of the weighted worlds [m]."""
    mass: float
    """The best world's object mass [kg]."""
    friction: float
    """The best world's object friction coefficient."""
    status: str
    """The track state."""
    mode_weights: Vector | None = None
    """The two pose modes' shares of the weights, (2,)."""


class SessionStatus(_Message):
    """A session's counters since it opened."""

    session: str
    """The session."""
    frames: int
    """Frames tracked."""
    gaps: int
    """Frames skipped over: seq numbers that never arrived before a later one."""
    duplicates: int
    """Frames dropped because their seq was the last one applied."""
    late: int
    """Frames dropped because their seq was older than the last one applied."""
    errors: int
    """Frames refused (malformed, wrong shape, non-finite)."""
    stale: int = 0
    """Frames dropped unapplied under overload: the session's queue was full (the newest are kept)
    or they waited longer than the service's bound."""
    resyncs: int = 0
    """Times the robot's seq jumped beyond the service's window and the session re-synchronised to it."""
    replays: int = 0
    """Signed frames, observations and queries refused as replays: a frame of an older epoch, or
    far behind in the same; an observation or query not newer than one already accepted."""
    latency_p50_ms: float
    """Median of the last 1000 frames' latencies, arrival to estimate [ms]."""
    latency_p99_ms: float
    """99th percentile of the same [ms]."""
    cost: float
    """The latest estimate's cost (dimensionless)."""
    spread_m: float
    """sqrt(trace) of the latest estimate's position covariance (the worlds' spread about the mean
    pose, with the reported floor) [m]."""
    last_error: str | None = None
    """The last refused frame's error, naming the field and the numbers."""
    observations: int = 0
    """Pose observations used."""
    observations_stale: int = 0
    """Pose observations dropped: older than the service's ``max_observation_age_s``."""
    reseeds_by_observation: int = 0
    """Times no world agreed with a confident pose observation and the worlds were re-seeded around it."""
    budget_ms: float = 0.0
    """The service's frame budget [ms] (0: none)."""
    load_ms: float = 0.0
    """The service's populations' p99 step times, summed [ms]."""
    contacts_explored: bool = False
    """Whether the session's worlds explore their contacts' softness and impratio: their lowest
    cost said the model's contacts are wrong (a session of 1024 worlds or more; the tracker's
    ``contact_gate_cost``)."""
    evidence: float = 1.0
    """How strongly the last update moved the session's worlds, 0 (open loop) to 1 (full strength):
    the latest estimate's ``evidence``."""
    residuals: dict[str, float] = Field(default_factory=dict)
    """What the lowest-cost world leaves unexplained over the last second, per sensing: ``joints``
    (RMS per joint) [rad or m], ``force`` (each fingertip force's magnitude) [N], ``touch`` (each
    touch zone's force) [N], for what the robot sends. It holds the sensors' noise and the model's
    mismatch: at most the noise to declare in the robot config (``joint_noise``, ``force_noise``,
    ``touch_noise``)."""
    joints_off: dict[str, float] = Field(default_factory=dict)
    """The model check: joints whose simulated motion runs from the measured one by more than the
    service's ``model_check`` over the last seconds, by name: their RMS difference [rad or m]. The
    robot config's servos are not the robot's; ``inhand-tracker calibrate`` fits them."""
