"""What the service sends beyond the robot's own estimates (ROS 2 topics, recordings, the live
view), behind one interface: the node keeps them in a list and calls each the same way."""

from __future__ import annotations

import logging
from collections.abc import Iterable

from inhand_tracker.protocol import Estimate, OpenSession, PoseObservation, RobotFrame, SessionInfo

__all__ = ["Output", "Outputs"]

log = logging.getLogger(__name__)


class Output:
    """An optional output of the service; every hook does nothing unless the output needs it.
    Called on the service's loop thread only."""

    name = "output"

    def warm(self, manager) -> None:
        """The service warms up (``manager``: its SessionManager): compile what the output runs."""

    def open(self, info: SessionInfo, request: OpenSession) -> None:
        """A session opened."""

    def frame(self, frame: RobotFrame) -> None:
        """A robot frame was accepted."""

    def observation(self, observation: PoseObservation) -> None:
        """A pose observation was accepted."""

    def estimate(self, estimate: Estimate) -> None:
        """An estimate went out to its robot."""

    def tick(self, sessions: dict) -> None:
        """The loop came round (``sessions``: the manager's, by id)."""

    def drop(self, session: str) -> None:
        """A session closed."""

    def close(self) -> None:
        """The service stops."""


class Outputs:
    """The service's outputs. A failing output is the output's problem, never the robot's: it is
    logged and the others go on; one that fails on a tick (it would fail on every one) is closed."""

    def __init__(self, outputs: Iterable[Output] = ()):
        self._outputs = list(outputs)

    def add(self, output: Output) -> None:
        self._outputs.append(output)

    def _each(self, hook: str, *args) -> None:
        for output in self._outputs:
            try:
                getattr(output, hook)(*args)
            except Exception:
                log.exception("the %s failed on %s", output.name, hook)

    def warm(self, manager) -> None:
        self._each("warm", manager)

    def open(self, info: SessionInfo, request: OpenSession) -> None:
        self._each("open", info, request)

    def frame(self, frame: RobotFrame) -> None:
        self._each("frame", frame)

    def observation(self, observation: PoseObservation) -> None:
        self._each("observation", observation)

    def estimate(self, estimate: Estimate) -> None:
        self._each("estimate", estimate)

    def drop(self, session: str) -> None:
        self._each("drop", session)

    def tick(self, sessions: dict) -> None:
        for output in list(self._outputs):
            try:
                output.tick(sessions)
            except Exception:
                log.exception("the %s failed; it is closed", output.name)
                self._outputs.remove(output)
                self._each_close(output)

    def close(self) -> None:
        for output in self._outputs:
            self._each_close(output)
        self._outputs.clear()

    @staticmethod
    def _each_close(output: Output) -> None:
        try:
            output.close()
        except Exception:
            log.exception("closing the %s failed", output.name)
