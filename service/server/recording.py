"""Every session recorded to a rosbag2 folder (setting ``record``): an MCAP file in the rosbag2
profile with what the robot sent, every estimate and a summary of the population, each a ROS 2
message with its schema, and the folder's ``metadata.yaml`` once the session closes, so ``ros2 bag``
and rosbags open it and ``inhand-tracker replay`` tracks it again offline. The layout is
:mod:`protocol.recording`'s."""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer
from ruamel.yaml import YAML

from inhand_tracker.protocol import (
    CHANNELS,
    PROTOCOL_VERSION,
    Estimate,
    OpenSession,
    PopulationSummary,
    PoseObservation,
    RobotFrame,
    SessionInfo,
)
from inhand_tracker.protocol.recording import PROFILE, SESSION_FIELDS, SESSION_METADATA
from inhand_tracker.protocol.ros2_records import RECORD_TYPES, encode_record, msg_definition, typestore

from .outputs import Output
from .ros2 import POSE_TYPE, TF_TYPE, TYPES, object_frame, pose_message, ros_namespace, tf_message, to_ros_time

__all__ = ["SessionRecorder"]

log = logging.getLogger(__name__)

_JOINTS = "sensor_msgs/msg/JointState"
_ROS = {"joint_states": _JOINTS, "pose": POSE_TYPE, "tf": TF_TYPE}
_FLUSH_S = 0.25
"""How often a recording's chunk is written out [s]: a process killed outright loses at most this."""


def _plain(value):
    """A metadata value as JSON: arrays as nested lists."""
    return value.tolist() if isinstance(value, np.ndarray) else value


class _File:
    """One session's rosbag2 folder: its MCAP file, channels and what metadata.yaml will say."""

    def __init__(self, folder: Path, info: SessionInfo, request: OpenSession, service: str, frame_id: str):
        folder.mkdir()
        self.folder, self.info, self.frame_id = folder, info, frame_id
        self.path = folder / f"{folder.name}_0.mcap"
        self.stream = self.path.open("wb")
        self.writer = Writer(self.stream, compression=CompressionType.ZSTD)
        self.writer.start(profile=PROFILE, library="inhand-tracker")
        self.channels: dict[str, int] = {}
        store = typestore()
        types = {role: name for role, (_, name) in RECORD_TYPES.items()} | _ROS
        for role, msg_type in types.items():
            # The protocol's records with their fields' units and meaning; ROS's own as ROS has them.
            if role in RECORD_TYPES:
                text = msg_definition(RECORD_TYPES[role][0])
            else:
                text = store.generate_msgdef(msg_type, ros_version=2)[0]
            sid = self.writer.register_schema(name=msg_type, encoding="ros2msg", data=text.encode())
            self.channels[role] = self.writer.register_channel(CHANNELS[role], "cdr", sid)
        # The granted values (info) over the asked ones (request), as the session was opened.
        known = {"service": service, "protocol": PROTOCOL_VERSION, **request.model_dump(), **info.model_dump()}
        opened = {k: known[k] for k in SESSION_FIELDS}
        self.writer.add_metadata(SESSION_METADATA, {k: json.dumps(_plain(v)) for k, v in opened.items()})
        self.sequence = 0
        self.flushed = time.monotonic()
        self.types = types
        self.counts = dict.fromkeys(types, 0)
        self.first_ns = self.last_ns = time.time_ns()

    def write(self, role: str, data: bytes, stamp: float) -> None:
        self.sequence += 1
        self.counts[role] += 1
        robot_ns, self.last_ns = round(stamp * 1e9), time.time_ns()
        self.writer.add_message(self.channels[role], self.last_ns, data, robot_ns, self.sequence)
        if time.monotonic() - self.flushed > _FLUSH_S:
            # The chunk written and handed to the OS: a process killed after this loses at most
            # _FLUSH_S, and the loader reads a file without its summary up to its last whole record.
            self.writer.flush()
            self.stream.flush()
            self.flushed = time.monotonic()

    def record(self, role: str, record, stamp: float) -> None:
        self.write(role, encode_record(role, record), stamp)

    def ros(self, role: str, message, stamp: float) -> None:
        self.write(role, bytes(TYPES.serialize_cdr(message, _ROS[role])), stamp)

    def close(self) -> None:
        self.writer.finish()
        self.stream.close()
        metadata = bag_metadata(self.path.name, self.types, self.counts, self.first_ns, self.last_ns)
        with (self.folder / "metadata.yaml").open("w") as out:
            YAML(typ="safe", pure=True).dump(metadata, out)


def bag_metadata(file: str, types: dict[str, str], counts: dict[str, int], first_ns: int, last_ns: int) -> dict:
    """rosbag2's metadata.yaml (version 8, as Jazzy writes it) of one MCAP file: written here, since
    the MCAP is ours (written as it goes, so that a crash loses a quarter second, which rosbags'
    writer does not do) and only its metadata is rosbag2's."""
    span = {"starting_time": {"nanoseconds_since_epoch": first_ns}, "duration": {"nanoseconds": last_ns - first_ns}}
    total = sum(counts.values())
    topics = [
        {
            "topic_metadata": {
                "name": CHANNELS[role], "type": types[role], "serialization_format": "cdr",
                "offered_qos_profiles": "", "type_description_hash": TYPES.hash_rihs01(types[role]),
            },
            "message_count": counts[role],
        }
        for role in types
    ]  # fmt: skip
    return {
        "rosbag2_bagfile_information": {
            "version": 8, "storage_identifier": "mcap", "relative_file_paths": [file], **span,
            "message_count": total, "topics_with_message_count": topics, "compression_format": "",
            "compression_mode": "", "files": [{"path": file, **span, "message_count": total}],
            "custom_data": {}, "ros_distro": "",
        }
    }  # fmt: skip


class SessionRecorder(Output):
    """The recordings of every open session, written by the service's loop thread. A recording
    that fails (a full disk, a read-only folder) stops for its session alone and says so through
    ``said(session, message)``; tracking never waits on it."""

    name = "recorder"

    def __init__(
        self, folder: str | Path, service: str, frame_id: str = "world", said: Callable[[str, str], None] | None = None
    ):
        self.folder = Path(folder).expanduser()
        self.service, self.frame_id = service, frame_id
        self.said = said or (lambda session, message: None)
        self._files: dict[str, _File] = {}
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:  # said at each open: the service itself goes on
            log.error("recordings: cannot make the folder %s (%s)", self.folder, exc)

    @contextlib.contextmanager
    def _guarded(self, session: str):
        """Run a session's recording work; a failure ends that recording and is said, not raised."""
        try:
            yield
        except Exception as exc:
            f = self._files.pop(session, None)
            if f is not None:
                with contextlib.suppress(Exception):
                    f.close()
            message = f"recording: stopped for this session: {type(exc).__name__}: {exc}"
            log.error("session %s: %s", session, message)
            self.said(session, message)

    def open(self, info: SessionInfo, request: OpenSession) -> None:
        # Named by the session's name (what a launch file knows it by; a namespace's ``/`` as ``.``)
        # and id (unique across runs).
        folder = self.folder / f"{(info.name or 'session').replace('/', '.')}_{info.session.rpartition('~')[2]}"
        with self._guarded(info.session):
            self._files[info.session] = _File(folder, info, request, self.service, self.frame_id)
            log.info("recording session %s to %s", info.session, folder)

    def frame(self, frame: RobotFrame) -> None:
        with self._guarded(frame.session):
            self._frame(frame)

    def _frame(self, frame: RobotFrame) -> None:
        f = self._files.get(frame.session)
        if f is None:
            return
        f.record("frame", frame, frame.stamp)
        joints = TYPES.types[_JOINTS](
            header=TYPES.types["std_msgs/msg/Header"](stamp=to_ros_time(frame.stamp), frame_id=f.frame_id),
            name=list(f.info.joint_names),
            position=np.asarray(frame.q, np.float64),
            velocity=np.zeros(0, np.float64),
            effort=np.zeros(0, np.float64),
        )
        f.ros("joint_states", joints, frame.stamp)

    def observation(self, observation: PoseObservation) -> None:
        with self._guarded(observation.session):
            if (f := self._files.get(observation.session)) is not None:
                f.record("observation", observation, observation.stamp)

    def estimate(self, estimate: Estimate) -> None:
        with self._guarded(estimate.session):
            self._estimate(estimate)

    def _estimate(self, estimate: Estimate) -> None:
        f = self._files.get(estimate.session)
        if f is None:
            return
        f.record("estimate", estimate, estimate.stamp)
        summary = PopulationSummary(
            seq=estimate.seq, stamp=estimate.stamp, worlds=f.info.worlds, cost=estimate.cost,
            spread_m=float(np.sqrt(np.trace(np.asarray(estimate.covariance)[:3, :3]))), mass=estimate.mass,
            friction=estimate.friction, status=estimate.status, mode_weights=estimate.mode_weights,
        )  # fmt: skip
        f.record("population", summary, estimate.stamp)
        f.ros("pose", pose_message(estimate, f.frame_id), estimate.stamp)
        child = object_frame(f.info.name or estimate.session, ros_namespace(self.service))  # as /tf has it live
        f.ros("tf", tf_message(estimate, f.frame_id, child), estimate.stamp)

    def drop(self, session: str) -> None:
        f = self._files.get(session)
        if f is not None:
            with self._guarded(session):
                f.close()
                self._files.pop(session, None)
                log.info("recording of session %s closed: %s", session, f.folder)

    def close(self) -> None:
        for session in list(self._files):
            self.drop(session)
