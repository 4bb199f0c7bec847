"""Trajectory files: a robot's frames as the protocol carries them, plus the ground truth.

A file is one msgpack map (arrays as in the codec: {dtype, shape, bytes}, never pickled)::

    format       "inhand-tracker/trajectory"
    version      TRAJECTORY_VERSION (a reader refuses other versions, naming both)
    name, robot, object, frame_rate [Hz], meta {str: str | float | int}
    frames       {stamp (F,) [s], then every field of protocol.SENSING as (F, ...) or nil
                  when the robot did not sense it}: exactly RobotFrame's fields
    truth        {initial_pose (7,), initial_q (D,), pose (F, 7), mass [kg], friction} | nil

Poses are position [m] and quaternion (x, y, z, w). A robot-side client replays ``frames`` over
Zenoh (``RobotFrame`` per row); ``truth`` is what an evaluation scores against and what a
tracker must never read. Imports only numpy and msgpack, so the light client can use it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import msgpack
import numpy as np

from .codec import DecodeError, pack_value, unpack_array
from .messages import RobotFrame
from .sensing import SENSING, SensingAttributes, check_sensing, sensing_field

__all__ = ["TRAJECTORY_FORMAT", "TRAJECTORY_VERSION", "GroundTruth", "Trajectory"]

TRAJECTORY_FORMAT = "inhand-tracker/trajectory"
TRAJECTORY_VERSION = 1
_MAX_FILE_BYTES = 256 << 20


@dataclass
class GroundTruth:
    """Where the object really was: never sent to the tracker."""

    initial_pose: np.ndarray
    """Object pose before the first frame, (7,)."""
    initial_q: np.ndarray
    """Joint positions before the first frame, (D,)."""
    pose: np.ndarray
    """Object pose after each frame, (F, 7)."""
    mass: float
    """Hidden object mass [kg]."""
    friction: float
    """Hidden friction coefficient."""


class Trajectory(SensingAttributes):
    """One robot's recorded frames (what the protocol carries) and, for benchmarks, the truth.

    The frames are the fields of :data:`protocol.SENSING`, each (F, ...) or None when the robot
    did not sense it, passed by name and read as attributes (``traj.controls``, ``traj.force``).
    """

    def __init__(
        self,
        name: str,
        robot: str,
        object: str,
        frame_rate: float,
        *,
        stamp: np.ndarray | None = None,
        truth: GroundTruth | None = None,
        meta: dict[str, str | float | int] | None = None,
        **sensing: np.ndarray | None,
    ):
        self.name, self.robot, self.object = name, robot, object
        self.frame_rate = float(frame_rate)
        """Frames per second [Hz]."""
        unknown = sorted(set(sensing) - {f.name for f in SENSING})
        if unknown:
            raise ValueError(f"trajectory '{name}': unknown fields {unknown} (known: {[f.name for f in SENSING]})")
        self.sensing: dict[str, np.ndarray | None] = {f.name: sensing.get(f.name) for f in SENSING}
        """Every field of protocol.SENSING, (F, ...) or None."""
        f, d = np.shape(self.sensing["controls"])
        per = lambda kind: next(  # noqa: E731 - the count of a kind of sensor, from the first field of it sent
            (np.shape(v)[1] for k, v in self.sensing.items() if v is not None and sensing_field(k).per == kind), 0
        )
        try:
            check_sensing(self.sensing, d, per("sensor"), lead=(f,), z=per("zone"))
        except ValueError as exc:
            raise ValueError(f"trajectory '{name}' {exc}") from None
        self.stamp = np.arange(f, dtype=np.float64) / self.frame_rate if stamp is None else stamp
        """Robot clock per frame, (F,) [s]."""
        self.truth = truth
        self.meta = dict(meta or {})
        """How it was made (demo kind, variant, physics gap, sensor noise)."""
        if truth is not None and np.shape(truth.pose) != (f, 7):
            raise ValueError(f"trajectory '{name}' truth.pose: expected shape {(f, 7)}, got {np.shape(truth.pose)}")

    @property
    def frames(self) -> int:
        return self.sensing["controls"].shape[0]

    def frame(self, i: int, session: str, seq: int | None = None, token: str = "") -> RobotFrame:
        """Row ``i`` as the message a robot sends (``token``: its session's secret)."""
        return RobotFrame(
            session=session,
            token=token,
            seq=i if seq is None else seq,
            stamp=float(self.stamp[i]),
            **{k: v[i] for k, v in self.sensing.items() if v is not None},
        )

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike) -> Path:
        frames = {"stamp": np.ascontiguousarray(self.stamp, dtype=np.float64)}
        frames |= {k: None if v is None else np.ascontiguousarray(v, dtype=np.float32) for k, v in self.sensing.items()}
        truth = None
        if self.truth is not None:
            t = self.truth
            truth = {
                "initial_pose": np.asarray(t.initial_pose, np.float32),
                "initial_q": np.asarray(t.initial_q, np.float32),
                "pose": np.asarray(t.pose, np.float32),
                "mass": float(t.mass),
                "friction": float(t.friction),
            }
        doc = {
            "format": TRAJECTORY_FORMAT,
            "version": TRAJECTORY_VERSION,
            "name": self.name,
            "robot": self.robot,
            "object": self.object,
            "frame_rate": float(self.frame_rate),
            "meta": dict(self.meta),
            "frames": frames,
            "truth": truth,
        }
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(msgpack.packb(doc, default=pack_value, use_bin_type=True))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Trajectory:
        """Read a trajectory file; a ValueError names the file and what is wrong with it."""
        path = Path(path)
        data = path.read_bytes()
        if len(data) > _MAX_FILE_BYTES:
            raise ValueError(f"{path}: {len(data)} bytes exceeds the limit of {_MAX_FILE_BYTES}")
        try:
            doc = msgpack.unpackb(data, object_hook=lambda o: unpack_array(o, _MAX_FILE_BYTES), raw=False)
        except DecodeError as exc:
            raise ValueError(f"{path}: {exc}") from exc
        except Exception as exc:
            raise ValueError(f"{path}: not a trajectory file ({type(exc).__name__}: {exc})") from exc
        if not isinstance(doc, dict) or doc.get("format") != TRAJECTORY_FORMAT:
            raise ValueError(
                f"{path}: not a trajectory file (format {doc.get('format') if isinstance(doc, dict) else None!r})"
            )
        if doc.get("version") != TRAJECTORY_VERSION:
            raise ValueError(
                f"{path}: trajectory format v{doc.get('version')}, this reader reads v{TRAJECTORY_VERSION}"
            )
        try:
            truth = doc["truth"] and GroundTruth(**doc["truth"])
            return cls(
                name=doc["name"],
                robot=doc["robot"],
                object=doc["object"],
                frame_rate=doc["frame_rate"],
                meta=doc["meta"],
                truth=truth or None,
                **doc["frames"],
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: malformed trajectory ({type(exc).__name__}: {exc})") from exc
