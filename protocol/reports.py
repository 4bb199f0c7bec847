"""What the service reports back: an estimate per frame, the population behind it for a
recording, and a session's status; their fields documented with unit and frame."""

from __future__ import annotations

from enum import IntEnum

from pydantic import Field

from .arrays import Matrix6, Pose, Poses, Vector
from .base import WireMessage

__all__ = ["Estimate", "PopulationSummary", "SessionStatus", "TrackState"]


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


class Estimate(WireMessage):
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
    dead_reckoning: float = 0.0
    """How far ``pose`` is the session's open-loop world's, which follows the robot's commands from
    the start estimate alone: 0, the population's, to 1, dead reckoning. Always 1 for a session of
    method OLP, and 0 for the others unless their ``optimizer.open_loop_ratio`` (while dead
    reckoning explains the sensing as well as the worlds do) or ``by_evidence`` (as far as the last
    update fell short of full strength) is on."""
    latency_ms: float
    """From the frame's arrival at the service to this estimate [ms]."""
    notice: str | None = None
    """What the robot should know about this frame, once: e.g. that its seq jumped and the
    session re-synchronised to it."""
    mac: str = ""
    """For a session opened with a ``client_key``: HMAC-SHA256 of this estimate with ``mac`` empty,
    keyed by the session's agreed secret (protocol.auth), so that its robot can tell it is the
    service's."""


class PopulationSummary(WireMessage):
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


class SessionStatus(WireMessage):
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
    ``touch_noise``). Once ``touch_noise`` is declared, ``touch`` is what lies beyond twice it."""
    joints_off: dict[str, float] = Field(default_factory=dict)
    """The model check: joints whose simulated motion runs from the measured one by more than the
    service's ``model_check`` over the last seconds, by name: their RMS difference [rad or m]. The
    robot config's servos are not the robot's; ``inhand-tracker calibrate`` fits them."""
