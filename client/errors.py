"""What a :class:`~.tracker_client.TrackerClient` raises besides TimeoutError and ValueError."""

from __future__ import annotations

from inhand_tracker.protocol import ErrorCode

__all__ = ["ServiceLost", "StaleEstimate", "TrackerError"]


class TrackerError(Exception):
    """The service refused a request: ``code`` (protocol ErrorCode), its message, and on
    ``capacity`` the other services that may have room."""

    def __init__(self, code: ErrorCode | str, message: str, others: list[str] | None = None):
        super().__init__(f"{code}: {message}" + (f" (other services: {', '.join(others)})" if others else ""))
        self.code, self.message, self.others = ErrorCode(code), message, list(others or [])


class StaleEstimate(RuntimeError):
    """The newest estimate answers a frame older than the caller allows: the service is not keeping
    up, stalled, or no longer tracks this session."""


class ServiceLost(ConnectionError):
    """The service's liveliness token went away while a session was open: it stopped or
    restarted, and the session is gone with it (:meth:`TrackerClient.reopen` starts a new one)."""
