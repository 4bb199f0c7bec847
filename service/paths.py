"""Where the project's files live: bundled data, configs and the trajectory cache."""

from __future__ import annotations

from pathlib import Path

__all__ = ["CACHE_DIR", "CONFIG_DIR", "DATA_DIR", "PROJECT_ROOT"]

PROJECT_ROOT = Path(__file__).resolve().parents[1]
"""What relative paths in the service's config (robots, objects) are relative to."""
DATA_DIR = PROJECT_ROOT / "data" / "trajectories"
"""The short trajectories shipped with the project (smoke suite, demo, speed benchmark)."""
CONFIG_DIR = PROJECT_ROOT / "configs"
"""The service's default configuration and the robot configs it names."""
CACHE_DIR = Path.home() / ".cache" / "inhand-tracker" / "trajectories"
"""Where the benchmarks write the longer trajectories they record."""
