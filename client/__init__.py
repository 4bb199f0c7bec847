"""The robot side: a light client of the tracking service (imports zenoh, msgpack, numpy and
pydantic only; never torch, warp or newton)."""

from .replay import NOISE_LEVELS, ReplayResult, noisy_start, replay
from .tracker_client import ServiceLost, StaleEstimate, TrackerClient, TrackerError
from .zenoh_session import check_endpoints, zenoh_config, zenoh_encoding

__all__ = [
    "NOISE_LEVELS",
    "ReplayResult",
    "ServiceLost",
    "StaleEstimate",
    "TrackerClient",
    "TrackerError",
    "check_endpoints",
    "noisy_start",
    "replay",
    "zenoh_config",
    "zenoh_encoding",
]
