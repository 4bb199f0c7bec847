"""`inhand-tracker`: the tracking service, the robot side's replay, the demo and the benchmarks.

Heavy imports (torch, warp, newton) happen inside the commands that need them, so `replay` and
`--help` stay light. The commands live beside this file by concern: the service and the robot
side (:mod:`.tracking`), the benchmarks (:mod:`.bench`), the robot's calibration
(:mod:`.calibrate`). Defaults live in the settings they belong to (ServiceConfig,
PopulationConfig, TrackerConfig, the protocol); an option left out takes that default.
"""

from __future__ import annotations

from typing import Annotated

import typer

from . import bench, calibrate, tracking  # noqa: F401  (their commands register on the apps)
from .common import app, version_callback

__all__ = ["app", "main"]


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=version_callback, is_eager=True, help="print the version and exit")
    ] = False,
) -> None:
    from inhand_tracker.service.logs import setup_logging

    setup_logging()


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (2 for a bad argument, with the reason)."""
    try:
        app(args=argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else int(exc.code is not None)
    return 0
