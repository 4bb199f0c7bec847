"""An open that waits for its population's build: the service answers it once the population is
built (on a fresh GPU machine, minutes), so the client waits for that instead of timing out, and
says meanwhile, in its log, that the service is building and how long the last build took."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from inhand_tracker.protocol import ServiceInfo

__all__ = ["BuildWatch"]

log = logging.getLogger("inhand_tracker.client")


class BuildWatch:
    """While in its ``with`` block, every ``every`` seconds after the first ``after``: ask
    ``info()`` and log when the service is building (the block is an open waiting on it)."""

    def __init__(self, info: Callable[[], ServiceInfo], after: float = 2.0, every: float = 10.0):
        self.info, self.after, self.every = info, after, every
        self.said: list[str] = []
        """What it logged, in order."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="inhand-open-watch", daemon=True)

    def __enter__(self) -> BuildWatch:
        self._thread.start()
        return self

    def __exit__(self, *_) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _watch(self) -> None:
        wait = self.after
        while not self._stop.wait(wait):
            wait = self.every
            try:
                info = self.info()
            except Exception:  # the open itself says what went wrong; this is only a progress note
                continue
            if info.building:
                last = f"the last build here took {info.build_s:.0f} s" if info.build_s else "its first build"
                self.said.append(f"service '{info.name}' is building a population for this open ({last}); waiting")
                log.info(self.said[-1])
