"""The service's configuration: a TOML file (configs/service.toml), overridable from the command
line and from environment variables INHAND_<KEY> (what a container sets)."""

from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, fields, replace
from pathlib import Path

from service.paths import CONFIG_DIR

__all__ = ["DEFAULT_CONFIG", "ServiceConfig", "load_config"]

DEFAULT_CONFIG = CONFIG_DIR / "service.toml"


@dataclass(frozen=True)
class ServiceConfig:
    name: str = "default"
    """The service's name: its keys live under inhand/v1/{name}."""
    device: str = "auto"
    """auto (CUDA when present, else CPU), cpu, cuda or cuda:N."""
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    """Zenoh endpoints to listen on."""
    connect: tuple[str, ...] = ()
    """Zenoh endpoints (a router, or peers) to connect to."""
    scouting: bool = False
    """Zenoh multicast scouting; off, so a service is found only where it is told to be."""
    groups: int = 8
    """Sessions per population: sessions with the same robot, object and K share one graph replay."""
    max_worlds: int = 65536
    """Worlds the service may hold in all."""
    robots: tuple[str, ...] = ("configs/robots/allegro.toml",)
    """Robot configs (TOML; relative paths are from the project root)."""
    robot_timeout_s: float = 3.0
    """A session whose robot's liveliness token is gone this long is closed and its worlds freed."""
    max_wait_s: float = 0.05
    """A population steps when every session sent a frame, or when a frame waited this long."""
    substeps: int = 8
    """Physics substeps per frame (even): fewer are faster and less accurate (docs/benchmarks.md)."""

    def __post_init__(self) -> None:
        if self.substeps < 2 or self.substeps % 2:
            raise ValueError(f"service substeps: expected a positive even number, got {self.substeps}")
        if self.groups < 1 or self.max_worlds < 1:
            raise ValueError(f"service groups and max_worlds: expected >= 1, got {self.groups}, {self.max_worlds}")
        if self.robot_timeout_s <= 0 or self.max_wait_s < 0:
            raise ValueError(
                f"service robot_timeout_s > 0 and max_wait_s >= 0, got {self.robot_timeout_s}, {self.max_wait_s}"
            )


def load_config(path: str | os.PathLike | None = None, **overrides) -> ServiceConfig:
    """The config in ``path`` (default configs/service.toml, if present), then INHAND_* variables,
    then ``overrides`` (None values ignored). A ValueError names the key and the value."""
    table: dict = {}
    path = Path(path) if path is not None else DEFAULT_CONFIG
    if path.exists():
        try:
            table = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"service config '{path}': {exc}") from exc
    elif path != DEFAULT_CONFIG:
        raise ValueError(f"service config: no such file '{path}'")
    known = {f.name: f for f in fields(ServiceConfig)}
    unknown = sorted(set(table) - set(known))
    if unknown:
        raise ValueError(f"service config '{path}': unknown keys {unknown} (known: {sorted(known)})")
    for key in known:
        env = os.environ.get(f"INHAND_{key.upper()}")
        if env is not None:
            table[key] = env.split(",") if key in ("listen", "connect", "robots") else env
    table |= {k: v for k, v in overrides.items() if v is not None}
    values = {}
    for key, value in table.items():
        kind = type(getattr(ServiceConfig(), key))
        try:
            if kind is tuple:
                values[key] = tuple(str(v) for v in ([value] if isinstance(value, str) else value) if v)
            elif kind is bool:
                values[key] = value if isinstance(value, bool) else str(value).lower() in ("1", "true", "yes")
            else:
                values[key] = kind(value)
        except (TypeError, ValueError):
            raise ValueError(f"service config {key}: expected {kind.__name__}, got {value!r}") from None
    return replace(ServiceConfig(), **values)
