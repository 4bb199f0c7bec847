"""ROS 2 without a bridge: every session's estimate published on the service's own Zenoh session
the way rmw_zenoh publishes a topic, so that a ROS 2 stack on rmw_zenoh (Tier 1 since Kilted) sees
``/inhand/session_<id>/pose`` (``geometry_msgs/msg/PoseWithCovarianceStamped``) and, optionally,
the object's frame on ``/tf`` without a bridge process.

What rmw_zenoh expects, after its design document (docs/design.md of ros2/rmw_zenoh):

- data on ``<domain>/<topic without its leading '/'>/<DDS type name>/<RIHS01 type hash>``, the
  payload CDR-encoded (little-endian, with its 4-byte encapsulation header);
- on every sample an attachment of the publisher's sequence number (int64), the source timestamp
  (int64, ns) and the publisher's GID (16 bytes, length-prefixed): rmw_zenoh's subscribers drop
  samples without it;
- liveliness tokens for the node (``NN``) and each publisher (``MP``), which ``ros2 node list`` and
  ``ros2 topic list`` read:
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>``
  with '/' in names written as '%'.

The messages, their CDR and their type hashes come from rosbags' ROS 2 type store; only the key
layout, the attachment and the tokens are written here, since no library on PyPI publishes as an
rmw_zenoh node on a session it does not own.
"""

from __future__ import annotations

import re
import secrets
import struct
import time
from dataclasses import dataclass

import numpy as np
import zenoh

from inhand_tracker.protocol import Estimate, OpenSession, SessionInfo
from inhand_tracker.protocol.ros2_records import typestore

from .outputs import Output

__all__ = [
    "POSE_TYPE",
    "TF_TYPE",
    "TYPES",
    "RosPublisher",
    "RosTopics",
    "node_token",
    "object_frame",
    "pose_message",
    "ros_namespace",
    "ros_topic",
    "tf_message",
    "to_ros_time",
    "topic_key",
    "topic_token",
]

TYPES = typestore()
"""The ROS 2 message types (Jazzy's definitions; the types used here are the same since Humble),
with the protocol's records (:mod:`protocol.ros2_records`)."""
POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"
_M = TYPES.types
_QOS = "::,{depth}:,:,:,,"
"""rmw_zenoh's QoS field of a token: reliable, volatile, keep last ``depth``, the rest default."""
_TF_DEPTH = 100
"""/tf's history depth, as tf2's broadcasters declare it (the poses keep ROS's default 10)."""
_NOT_A_NAME = re.compile(r"[^A-Za-z0-9_/]")
"""What a ROS name (tokens and the ``/`` of their namespace) cannot hold."""


def ros_namespace(service: str) -> str:
    """The ROS 2 namespace of a service's node and topics: the root for the service named
    ``default``, else ``/<its name>``, so that two services on one network never share a topic."""
    return "/" if service == "default" else "/" + _NOT_A_NAME.sub("_", service)


def ros_topic(name: str, leaf: str = "pose", namespace: str = "/") -> str:
    """The ROS 2 topic of a session's ``leaf``, by the session's name (a ROS name token), in the
    service's namespace."""
    return f"{namespace.rstrip('/')}/inhand/{_NOT_A_NAME.sub('_', name)}/{leaf}"


def object_frame(name: str, namespace: str = "/") -> str:
    """The TF frame of a session's object: the session's name, under the service's namespace."""
    frame = _NOT_A_NAME.sub("_", name)
    return frame if namespace == "/" else f"{namespace.strip('/')}/{frame}"


def to_ros_time(stamp: float):
    """``builtin_interfaces/msg/Time`` of a robot clock [s]."""
    sec = int(np.floor(stamp))
    return _M["builtin_interfaces/msg/Time"](sec=sec, nanosec=min(round((stamp - sec) * 1e9), 999_999_999))


def _pose(pose: np.ndarray):
    p = pose.astype(np.float64)
    return _M["geometry_msgs/msg/Pose"](
        position=_M["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
        orientation=_M["geometry_msgs/msg/Quaternion"](x=p[3], y=p[4], z=p[5], w=p[6]),
    )


def pose_message(estimate: Estimate, frame_id: str):
    """The estimate as ``PoseWithCovarianceStamped``: stamped with the robot's clock of the frame it
    answers, in ``frame_id`` (the robot's world frame). ROS's covariance is row-major over (x, y, z,
    rotation about x, y, z) in that frame: the estimate's own."""
    header = _M["std_msgs/msg/Header"](stamp=to_ros_time(estimate.stamp), frame_id=frame_id)
    covariance = np.asarray(estimate.covariance, np.float64).reshape(36)
    return _M[POSE_TYPE](
        header=header, pose=_M["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(estimate.pose), covariance=covariance)
    )


def tf_message(estimate: Estimate, frame_id: str, child_frame_id: str):
    """The estimate as one transform on ``/tf``: the object's frame under ``frame_id``."""
    pose = _pose(estimate.pose)
    at = pose.position
    transform = _M["geometry_msgs/msg/Transform"](
        translation=_M["geometry_msgs/msg/Vector3"](x=at.x, y=at.y, z=at.z), rotation=pose.orientation
    )
    header = _M["std_msgs/msg/Header"](stamp=to_ros_time(estimate.stamp), frame_id=frame_id)
    stamped = _M["geometry_msgs/msg/TransformStamped"](
        header=header, child_frame_id=child_frame_id, transform=transform
    )
    return _M[TF_TYPE](transforms=[stamped])


def _dds_name(msg_type: str) -> str:
    package, kind, name = msg_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def _mangle(name: str) -> str:
    return name.replace("/", "%") if name not in ("", "/") else "%"


def topic_key(domain_id: int, topic: str, msg_type: str, digest: str | None = None) -> str:
    """rmw_zenoh's data key of a topic; without ``digest``, of any type hash (ROS 2 distributions
    hash the same type differently, Humble not at all)."""
    return f"{domain_id}/{topic.lstrip('/')}/{_dds_name(msg_type)}/{digest or '*'}"


def node_token(domain_id: int, zid: str, node: str, namespace: str) -> str:
    """The liveliness token of a node, which ``ros2 node list`` reads."""
    return f"@ros2_lv/{domain_id}/{zid}/0/0/NN/%/{_mangle(namespace)}/{node}"


def topic_token(
    domain_id: int,
    zid: str,
    node: str,
    namespace: str,
    entity: int,
    kind: str,
    topic: str,
    msg_type: str,
    depth: int = 10,
) -> str:
    """The liveliness token of a node's publisher (``MP``) or subscription (``MS``) on a topic,
    which ``ros2 topic info`` reads, with the history ``depth`` it keeps."""
    dds, digest, ns = _dds_name(msg_type), TYPES.hash_rihs01(msg_type), _mangle(namespace)
    qos = _QOS.format(depth=depth)
    return f"@ros2_lv/{domain_id}/{zid}/0/{entity}/{kind}/%/{ns}/{node}/{_mangle(topic)}/{dds}/{digest}/{qos}"


@dataclass
class RosPublisher:
    """One rmw_zenoh publisher: its data key, its liveliness token, its sequence and GID."""

    topic: str
    msg_type: str
    key: str
    token: zenoh.LivelinessToken
    publisher: zenoh.Publisher
    gid: bytes
    seq: int = 0

    def put(self, message) -> None:
        self.seq += 1
        # rmw_zenoh's attachment, serialised as zenoh-ext does (int64, int64, then the 16 GID bytes
        # with their LEB128 length): no Python library writes it.
        attachment = struct.pack("<qqB", self.seq, time.time_ns(), len(self.gid)) + self.gid
        self.publisher.put(bytes(TYPES.serialize_cdr(message, self.msg_type)), attachment=attachment)

    def close(self) -> None:
        self.token.undeclare()
        self.publisher.undeclare()


class RosTopics(Output):
    """The service as one ROS 2 node (``inhand_tracker`` in the service's namespace), with a pose
    publisher per session and, when ``tf`` is on, one ``/tf`` publisher for all of them."""

    name = "ROS 2 topics"

    def __init__(
        self,
        session: zenoh.Session,
        domain_id: int = 0,
        frame_id: str = "world",
        tf: bool = False,
        namespace: str = "/",
    ):
        self.session, self.domain_id, self.frame_id, self.namespace = session, domain_id, frame_id, namespace
        self.node = "inhand_tracker"
        self._zid = str(session.info.zid())
        self._entities = 0
        self._node_token = session.liveliness().declare_token(node_token(domain_id, self._zid, self.node, namespace))
        self._poses: dict[str, RosPublisher] = {}
        self._children: dict[str, str] = {}
        self._tf = self._declare("/tf", TF_TYPE, _TF_DEPTH) if tf else None

    def _declare(self, topic: str, msg_type: str, depth: int = 10) -> RosPublisher:
        self._entities += 1
        key = topic_key(self.domain_id, topic, msg_type, TYPES.hash_rihs01(msg_type))
        entity = self._entities
        token = topic_token(self.domain_id, self._zid, self.node, self.namespace, entity, "MP", topic, msg_type, depth)
        return RosPublisher(
            topic,
            msg_type,
            key,
            self.session.liveliness().declare_token(token),
            self.session.declare_publisher(key, express=True),
            secrets.token_bytes(16),
        )

    def open(self, info: SessionInfo, request: OpenSession | None = None) -> None:
        """Start publishing the session's estimates on its ROS 2 pose topic."""
        name = info.name or info.session
        self._poses[info.session] = self._declare(ros_topic(name, namespace=self.namespace), POSE_TYPE)
        self._children[info.session] = object_frame(name, self.namespace)

    def estimate(self, estimate: Estimate) -> None:
        pub = self._poses.get(estimate.session)
        if pub is None:
            return
        pub.put(pose_message(estimate, self.frame_id))
        if self._tf is not None:
            self._tf.put(tf_message(estimate, self.frame_id, self._children[estimate.session]))

    def drop(self, session: str) -> None:
        pub = self._poses.pop(session, None)
        self._children.pop(session, None)
        if pub is not None:
            pub.close()

    def close(self) -> None:
        for session in list(self._poses):
            self.drop(session)
        if self._tf is not None:
            self._tf.close()
        self._node_token.undeclare()
