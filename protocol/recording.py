"""Session recordings: one rosbag2 folder per session (an MCAP file in the rosbag2 profile and its
``metadata.yaml``), as the service writes them (setting ``record``) and as ``inhand-tracker
replay`` reads them back (the folder or its ``.mcap``). Every channel is a ROS 2 message in CDR
with its ``ros2msg`` schema in the file, so tools that read rosbag2 (``ros2 bag``, rosbags) open
the folder and take the types from the file itself.

Channels (topic, ROS 2 type):

    /inhand/frame         inhand_tracker/msg/RobotFrame: what the robot sent, exactly, without its token
    /inhand/observation   inhand_tracker/msg/PoseObservation, without its token
    /inhand/estimate      inhand_tracker/msg/Estimate
    /inhand/population    inhand_tracker/msg/PopulationSummary: the worlds after each frame
    /inhand/joint_states  sensor_msgs/msg/JointState: the robot's measured joints
    /inhand/pose          geometry_msgs/msg/PoseWithCovarianceStamped: the estimate
    /tf                   tf2_msgs/msg/TFMessage: the object's frame under the world frame

The inhand_tracker types are the protocol's messages (:mod:`.ros2_records`). The session's open is
the metadata record ``inhand.session`` (SESSION_FIELDS, every value a JSON text). Log times are the
service's clock, publish times the robot's [ns].

Imports numpy, msgpack, mcap and rosbags only: the light client reads recordings.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .reports import Estimate, PopulationSummary
from .ros2_records import decode_record
from .sensing import SENSING
from .trajectory import Trajectory

__all__ = [
    "CHANNELS",
    "PROFILE",
    "SESSION_FIELDS",
    "SESSION_METADATA",
    "SessionRecording",
    "is_recording",
    "load_trajectory",
    "recording_file",
]

CHANNELS = {
    "frame": "/inhand/frame",
    "observation": "/inhand/observation",
    "estimate": "/inhand/estimate",
    "population": "/inhand/population",
    "joint_states": "/inhand/joint_states",
    "pose": "/inhand/pose",
    "tf": "/tf",
}
"""The topic of each channel, by role."""
SESSION_METADATA = "inhand.session"
SESSION_FIELDS = (
    "session", "service", "protocol", "robot", "object", "method", "worlds", "p0", "sigma_t", "sigma_r", "q0",
    "joint_names", "sensor_names", "overrides",
)  # fmt: skip
"""The open's fields in the metadata record."""
PROFILE = "ros2"
"""The MCAP profile of a recording: rosbag2's."""


@dataclass
class SessionRecording:
    """A recorded session, read back."""

    opened: dict
    """The session's open (SESSION_FIELDS), p0 and q0 as arrays."""
    trajectory: Trajectory
    """What the robot sent, as a trajectory without ground truth."""
    estimates: list[Estimate] = field(default_factory=list)
    """Every estimate the service published, in seq order."""
    population: list[PopulationSummary] = field(default_factory=list)
    """The population's summary per frame."""

    @classmethod
    def load(cls, path: str | os.PathLike) -> SessionRecording:
        """The recording in ``path``; one cut short (the service killed, the disk full) is read up
        to its last whole record."""
        path = recording_file(path)
        metadata, messages = _read_mcap(path)
        if SESSION_METADATA not in metadata:
            raise ValueError(f"recording '{path}': no '{SESSION_METADATA}' metadata: not a session recording")
        opened = {k: json.loads(v) for k, v in metadata[SESSION_METADATA].items()}
        frames, estimates, population = [], [], []
        roles = {CHANNELS[k]: k for k in ("frame", "estimate", "population")}
        for topic, data in messages:
            role = roles.get(topic)
            if role is None:
                continue
            doc = decode_record(role, data)
            if role == "frame":
                frames.append(doc)
            elif role == "estimate":
                estimates.append(Estimate.model_validate(doc))
            else:
                population.append(PopulationSummary.model_validate(doc))
        if not frames:
            raise ValueError(f"recording '{path}': no frames on {CHANNELS['frame']}")
        opened["p0"] = np.asarray(opened["p0"], np.float32)
        if opened.get("q0") is not None:
            opened["q0"] = np.asarray(opened["q0"], np.float32)
        frames.sort(key=lambda d: (d.get("epoch", 0), d["seq"]))  # a counter restart opens a new epoch
        stamps = np.array([d["stamp"] for d in frames], np.float64)
        steps = np.diff(stamps)
        rate = 1.0 / float(np.median(steps)) if len(steps) and np.median(steps) > 0 else 30.0
        names = [k for k in frames[0] if k in _SENSED]
        sensing = {k: None if frames[0][k] is None else np.asarray([d[k] for d in frames], np.float32) for k in names}
        trajectory = Trajectory(
            path.stem, opened["robot"], opened["object"], rate, stamp=stamps, meta={"recording": str(path)},
            **sensing,
        )  # fmt: skip
        estimates.sort(key=lambda e: e.seq)
        return cls(opened, trajectory, estimates, population)


_SENSED = frozenset(f.name for f in SENSING)
"""The frame's sensing fields; the rest of a recorded frame is its header (session, seq, epoch, stamp)."""


def _read_mcap(path: Path) -> tuple[dict[str, dict[str, str]], list[tuple[str, bytes]]]:
    """The metadata records by name and every message as (topic, data) in log-time order. A file
    without its summary (written by a process that was killed, or cut by a full disk) is read
    record by record up to where it breaks off: mcap's reader needs the summary, and no library
    reads a truncated file, so the stream is walked here."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap.records import Channel, Message, Metadata
    from mcap.stream_reader import StreamReader

    try:
        with path.open("rb") as f:
            reader = make_reader(f)
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            messages = [(c.topic, m.data) for _, c, m in reader.iter_messages(log_time_order=True)]
            return metadata, messages
    except (McapError, EOFError, ValueError, KeyError, AssertionError, struct.error):
        pass  # no summary: walk the records
    metadata, channels, timed = {}, {}, []
    with path.open("rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False, emit_chunks=False).records:
                if isinstance(record, Metadata):
                    metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message) and record.channel_id in channels:
                    timed.append((record.log_time, channels[record.channel_id], record.data))
        except (McapError, EOFError, ValueError, KeyError, AssertionError, struct.error, _chunk_error()):
            pass  # the file breaks off here: keep what came before
    timed.sort(key=lambda t: t[0])
    return metadata, [(topic, data) for _, topic, data in timed]


def _chunk_error() -> type[Exception]:
    """What a cut-off compressed chunk raises when decompressed."""
    try:
        import zstandard

        return zstandard.ZstdError
    except ImportError:  # pragma: no cover - mcap brings zstandard
        return ValueError


def is_recording(path: str | os.PathLike) -> bool:
    """A session recording: a rosbag2 folder, or its ``.mcap`` file."""
    path = Path(path)
    return path.suffix == ".mcap" or path.is_dir()


def recording_file(path: str | os.PathLike) -> Path:
    """The MCAP file of a recording: ``path`` itself, or the one file of the rosbag2 folder ``path``
    (a folder without its metadata.yaml, which a killed service leaves, is read too)."""
    path = Path(path)
    if not path.is_dir():
        return path
    files = sorted(path.glob("*.mcap"))
    if len(files) != 1:
        raise ValueError(f"recording '{path}': expected one .mcap file in the folder, found {len(files)}")
    return files[0]


def load_trajectory(path: str | os.PathLike) -> Trajectory:
    """The trajectory of a ``.traj`` file, or what the robot sent in a session recording (a rosbag2
    folder or its ``.mcap``)."""
    return SessionRecording.load(path).trajectory if is_recording(path) else Trajectory.load(path)
