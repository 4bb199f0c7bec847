"""The service on Zenoh: its configuration, the sessions (each a group of a shared population)
and the node whose one loop thread owns the GPU."""

from .admission import ServiceError
from .config import ServiceConfig, load_config
from .node import TrackerNode
from .sessions import SessionManager

__all__ = ["ServiceConfig", "ServiceError", "SessionManager", "TrackerNode", "load_config"]
