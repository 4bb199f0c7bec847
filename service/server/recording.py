"""Every session recorded to an MCAP file (setting ``record``): what the robot sent, every
estimate and a summary of the population, with ROS 2 message types where they exist, so Foxglove
opens it and ``inhand-tracker replay`` tracks it again offline. The layout is
:mod:`protocol.recording`'s."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer

from protocol import CHANNELS, PROTOCOL_VERSION, Estimate, OpenSession, PoseObservation, RobotFrame, SessionInfo
from protocol.recording import SESSION_FIELDS, SESSION_METADATA

from .outputs import Output
from .ros2 import POSE_TYPE, TF_TYPE, TYPES, object_frame, pose_message, tf_message, to_ros_time

__all__ = ["SessionRecorder"]

log = logging.getLogger(__name__)

_JOINTS = "sensor_msgs/msg/JointState"
_ROS = {"joint_states": _JOINTS, "pose": POSE_TYPE, "tf": TF_TYPE}
_JSON = {"frame": RobotFrame, "observation": PoseObservation, "estimate": Estimate, "population": None}


def _plain(value):
    """A message field as JSON: arrays as nested lists."""
    return value.tolist() if isinstance(value, np.ndarray) else value


class _File:
    """One session's MCAP file and its channels."""

    def __init__(self, path: Path, info: SessionInfo, request: OpenSession, service: str, frame_id: str):
        self.path, self.info, self.frame_id = path, info, frame_id
        self.stream = path.open("wb")
        self.writer = Writer(self.stream, compression=CompressionType.ZSTD)
        self.writer.start(profile="", library="inhand-tracker")
        self.channels: dict[str, int] = {}
        for role, model in _JSON.items():
            title = model.__name__ if model else "PopulationSummary"
            schema = json.dumps({"title": title, "type": "object", "description": (model.__doc__ or "").strip()})
            sid = self.writer.register_schema(name=f"inhand.{title}", encoding="jsonschema", data=schema.encode())
            self.channels[role] = self.writer.register_channel(CHANNELS[role], "json", sid)
        for role, msg_type in _ROS.items():
            text = TYPES.generate_msgdef(msg_type, ros_version=2)[0]
            sid = self.writer.register_schema(name=msg_type, encoding="ros2msg", data=text.encode())
            self.channels[role] = self.writer.register_channel(CHANNELS[role], "cdr", sid)
        # The granted values (info) over the asked ones (request), as the session was opened.
        known = {"service": service, "protocol": PROTOCOL_VERSION, **request.model_dump(), **info.model_dump()}
        opened = {k: known[k] for k in SESSION_FIELDS}
        self.writer.add_metadata(SESSION_METADATA, {k: json.dumps(_plain(v)) for k, v in opened.items()})
        self.sequence = 0

    def write(self, role: str, data: bytes, stamp: float) -> None:
        self.sequence += 1
        robot_ns = round(stamp * 1e9)
        self.writer.add_message(self.channels[role], time.time_ns(), data, robot_ns, self.sequence)

    def json(self, role: str, doc: dict, stamp: float) -> None:
        self.write(role, json.dumps({k: _plain(v) for k, v in doc.items()}).encode(), stamp)

    def ros(self, role: str, message, stamp: float) -> None:
        self.write(role, bytes(TYPES.serialize_cdr(message, _ROS[role])), stamp)

    def close(self) -> None:
        self.writer.finish()
        self.stream.close()


class SessionRecorder(Output):
    """The recordings of every open session, written by the service's loop thread."""

    name = "recorder"

    def __init__(self, folder: str | Path, service: str, frame_id: str = "world"):
        self.folder = Path(folder).expanduser()
        self.folder.mkdir(parents=True, exist_ok=True)
        self.service, self.frame_id = service, frame_id
        self._files: dict[str, _File] = {}

    def open(self, info: SessionInfo, request: OpenSession) -> None:
        path = self.folder / f"{info.session}.mcap"
        self._files[info.session] = _File(path, info, request, self.service, self.frame_id)
        log.info("recording session %s to %s", info.session, path)

    def frame(self, frame: RobotFrame) -> None:
        f = self._files.get(frame.session)
        if f is None:
            return
        f.json("frame", frame.model_dump(exclude={"token"}), frame.stamp)
        joints = TYPES.types[_JOINTS](
            header=TYPES.types["std_msgs/msg/Header"](stamp=to_ros_time(frame.stamp), frame_id=f.frame_id),
            name=list(f.info.joint_names),
            position=np.asarray(frame.q, np.float64),
            velocity=np.zeros(0, np.float64),
            effort=np.zeros(0, np.float64),
        )
        f.ros("joint_states", joints, frame.stamp)

    def observation(self, observation: PoseObservation) -> None:
        if (f := self._files.get(observation.session)) is not None:
            f.json("observation", observation.model_dump(exclude={"token"}), observation.stamp)

    def estimate(self, estimate: Estimate) -> None:
        f = self._files.get(estimate.session)
        if f is None:
            return
        f.json("estimate", estimate.model_dump(), estimate.stamp)
        spread = float(np.sqrt(np.trace(np.asarray(estimate.covariance)[:3, :3])))
        summary = {
            "seq": estimate.seq, "worlds": f.info.worlds, "cost": estimate.cost, "spread_m": spread,
            "mass": estimate.mass, "friction": estimate.friction, "status": estimate.status,
            "mode_weights": estimate.mode_weights,
        }  # fmt: skip
        f.json("population", summary, estimate.stamp)
        f.ros("pose", pose_message(estimate, f.frame_id), estimate.stamp)
        f.ros("tf", tf_message(estimate, f.frame_id, object_frame(f.info.name or estimate.session)), estimate.stamp)

    def drop(self, session: str) -> None:
        f = self._files.pop(session, None)
        if f is not None:
            f.close()
            log.info("recording of session %s closed: %s", session, f.path)

    def close(self) -> None:
        for session in list(self._files):
            self.drop(session)
