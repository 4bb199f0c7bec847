"""What the service and the live view's drawing process say to each other over their pipe, declared
once for both sides (:mod:`.viewer` sends the first five, :mod:`.view_drawing` the last three)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inhand_tracker.sim_backend import ObjectSpec, PopulationConfig, RobotSpec

__all__ = ["Close", "Draw", "Drawn", "EstimateView", "Failed", "Panel", "Ready", "Show", "Warm", "layout"]


@dataclass(frozen=True)
class EstimateView:
    """What the view draws of an estimate."""

    pose: np.ndarray
    """The estimate, (7,): position [m] and quaternion (x, y, z, w)."""
    mean: np.ndarray
    """The weighted mean position, (3,) [m]."""
    covariance: np.ndarray
    """The position's covariance, (3, 3) [m^2]."""


def layout(K: int, bodies: int, tips: int) -> dict[str, tuple[int, int]]:
    """Where each array lies in the shared float32 buffer: name -> (start, stop)."""
    sizes = {"body_q": K * bodies * 7, "weights": K, "tips": tips * 3}
    stops = np.cumsum(list(sizes.values()))
    return {name: (int(stop - size), int(stop)) for (name, size), stop in zip(sizes.items(), stops, strict=True)}


# ------------------------------------------------------------------ service -> drawing
@dataclass(frozen=True)
class Warm:
    """Draw one world of this robot and object once, so a browser's first drawing compiles nothing."""

    robot: RobotSpec
    object: ObjectSpec
    config: PopulationConfig


@dataclass(frozen=True)
class Show:
    """A new session or group: build a replica of its K worlds; their arrays come in ``memory``."""

    robot: RobotSpec
    object: ObjectSpec
    config: PopulationConfig
    worlds: int
    """K."""
    memory: str
    """The shared memory's name, laid out by :func:`layout`."""
    sensors: int
    """The robot's force sensors: the real fingertips drawn."""


@dataclass(frozen=True)
class Panel:
    """The panel's text alone (nothing moved)."""

    text: str
    sessions: tuple[str, ...]
    """The sessions the browser may pick, by id."""


@dataclass(frozen=True)
class Draw:
    """The shared memory holds a new snapshot: draw it, with the estimate and the panel."""

    estimate: EstimateView | None
    text: str
    sessions: tuple[str, ...]


@dataclass(frozen=True)
class Close:
    """The service stops the view."""


# ------------------------------------------------------------------ drawing -> service
@dataclass(frozen=True)
class Ready:
    """The drawing process serves on ``port``."""

    port: int


@dataclass(frozen=True)
class Failed:
    """The drawing process failed, and why."""

    reason: str


@dataclass(frozen=True)
class Drawn:
    """What the browsers ask: the session picked and how many watch; ``done`` after a message was
    drawn (the process is idle), else sent when either changed."""

    choice: str
    clients: int
    done: bool
