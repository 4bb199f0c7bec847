"""The robot side: a light client of the tracking service (imports zenoh, msgpack, numpy and
pydantic only; never torch, warp or newton)."""

from .replay import noisy_start, replay
from .tracker_client import TrackerClient, TrackerError

__all__ = ["TrackerClient", "TrackerError", "noisy_start", "replay"]
