"""Progress of long benchmark runs."""

from __future__ import annotations

import sys

from tqdm import tqdm

__all__ = ["progress_bar"]


def progress_bar(total: int, label: str, unit: str = "it", disable: bool = False) -> tqdm:
    """A progress bar on stderr: redrawn in place on a terminal; in a log (not a terminal) one
    line every 10 s, so a CI or container log is not flooded with carriage returns."""
    terminal = sys.stderr.isatty()
    return tqdm(
        total=total,
        desc=label,
        unit=unit,
        unit_scale=True,
        file=sys.stderr,
        disable=disable,
        dynamic_ncols=terminal,
        mininterval=0.5 if terminal else 10.0,
        maxinterval=10.0 if terminal else 60.0,
        ascii=not terminal,
    )
