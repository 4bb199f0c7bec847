"""Where the project's files live: bundled data, configs and the trajectory cache."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["CACHE_DIR", "CONFIG_DIR", "DATA_DIR", "PROJECT_ROOT", "resolve"]

_CHECKOUT = Path(__file__).resolve().parents[1]
PROJECT_ROOT = _CHECKOUT if (_CHECKOUT / "configs").is_dir() else Path(__file__).resolve().parent / "bundled"
"""Where configs/ and data/ are: the source checkout, or the copy an installed wheel carries."""
DATA_DIR = PROJECT_ROOT / "data" / "trajectories"
"""The short trajectories shipped with the project (smoke suite, demo, speed benchmark)."""
CONFIG_DIR = PROJECT_ROOT / "configs"
"""The service's default configuration and the robot configs it names."""
CACHE_DIR = Path.home() / ".cache" / "inhand-tracker" / "trajectories"
"""Where the benchmarks write the longer trajectories they record."""


def resolve(path: str | os.PathLike) -> Path:
    """A path from a config: absolute, or relative to the working directory where it exists there
    (a user's own robot), else to the project (the bundled configs, ``configs/robots/allegro.toml``)."""
    path = Path(path).expanduser()
    if path.is_absolute() or path.exists():
        return path
    return PROJECT_ROOT / path
