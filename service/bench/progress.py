"""Progress of long benchmark runs."""

from __future__ import annotations

import logging
import sys

from tqdm import tqdm

__all__ = ["progress_bar"]

log = logging.getLogger("inhand_tracker.progress")


class _LoggedLines(tqdm):
    """tqdm's meter as a log line instead of a bar redrawn with carriage returns: what a CI or
    container log (not a terminal) can read."""

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        log.info(msg or str(self))
        return True


def progress_bar(total: int, label: str, unit: str = "it", disable: bool = False) -> tqdm:
    """A bar redrawn in place on a terminal; elsewhere a logged line every 10 s."""
    if sys.stderr.isatty():
        return tqdm(total=total, desc=label, unit=unit, unit_scale=True, file=sys.stderr, disable=disable)
    return _LoggedLines(total=total, desc=label, unit=unit, unit_scale=True, disable=disable, mininterval=10.0)
