"""The robot side: a light client of the tracking service (imports zenoh, msgpack, numpy and
pydantic only; never torch, warp or newton)."""

from .replay import ReplayResult, noisy_start, replay
from .tracker_client import TrackerClient, TrackerError

__all__ = ["ReplayResult", "TrackerClient", "TrackerError", "noisy_start", "replay"]
