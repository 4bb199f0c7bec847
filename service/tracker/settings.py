"""Every tracker and physics setting a user may change, by one dotted name, the path to it in the
settings' nesting: ``update_every``, ``exploration.jitter_bandwidth``, ``optimizer.min_separation``,
``cost.joints`` (a cost term's weight), ``population.impratio`` (the worlds' physics).

A session's ``overrides``, ``bench accuracy --set`` and a benchmark's record of what it changed all
speak these names; this registry is the only list of them. Values are checked by the settings'
own dataclasses, whose errors name the setting and the numbers."""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields, replace

from inhand_tracker.sim_backend import PopulationConfig, RobotSpec

from .config import TRACKER_GROUPS, TrackerConfig
from .cost import TERM_NAMES, WEIGHTS, CostConfig
from .optimizers import OptimizerConfig

__all__ = [
    "SETTING_KINDS",
    "UNCHECKED_PALM",
    "Setting",
    "changed",
    "parse",
    "registry",
    "robot_defaults",
    "split",
    "tracker_config",
    "unchecked_palms",
]

SETTING_KINDS = (bool, int, float, str)
"""What a setting may be: a flag, a number or a name (a friction cone, an integrator)."""
_NOT_SETTINGS = {
    "optimizer": {"method"},
    "population": {"groups", "worlds", "frame_rate", "device", "use_graph", "seed"},
}
"""Fields that are a run's layout, not a setting: the service and the benchmarks choose them."""


@dataclass(frozen=True)
class Setting:
    """One setting: its dotted name, its type, and who may change it."""

    name: str
    kind: type
    session: bool
    """A session's overrides may change it: the worlds' physics (``population.*``) are the
    service's, shared by every session of a population."""


def _kind(f, default) -> type | None:
    if type(default) in SETTING_KINDS:
        return type(default)
    if default is None:  # an optional number (None: the library's own default) is set as the number
        return next((k for k in SETTING_KINDS if f.type == f"{k.__name__} | None"), None)
    return None


@functools.cache
def registry() -> dict[str, Setting]:
    """Every setting by its dotted name."""
    out: dict[str, Setting] = {}
    top = TrackerConfig()
    for f in fields(TrackerConfig):
        if (kind := _kind(f, getattr(top, f.name))) is not None:
            out[f.name] = Setting(f.name, kind, session=True)
    groups = {g: type(getattr(top, g)) for g in sorted(TRACKER_GROUPS)}
    for prefix, cls in {**groups, "optimizer": OptimizerConfig, "cost": CostConfig}.items():
        default = cls()
        for f in fields(cls):
            if f.name in _NOT_SETTINGS.get(prefix, ()):
                continue
            if (kind := _kind(f, getattr(default, f.name))) is not None:
                out[f"{prefix}.{f.name}"] = Setting(f"{prefix}.{f.name}", kind, session=True)
    out |= {f"cost.{t}": Setting(f"cost.{t}", float, session=True) for t in TERM_NAMES}
    physics = PopulationConfig()
    for f in fields(PopulationConfig):
        if f.name not in _NOT_SETTINGS["population"] and (kind := _kind(f, getattr(physics, f.name))) is not None:
            out[f"population.{f.name}"] = Setting(f"population.{f.name}", kind, session=False)
    return out


def _unknown(name: str, allowed: Iterable[str]) -> ValueError:
    """An unknown name's error: the dotted spelling where the name is a setting's last part."""
    spelled = [n for n in allowed if n.rpartition(".")[2] == name]
    if spelled:
        return ValueError(f"'{name}': settings are named by their group, e.g. '{spelled[0]}'")
    return ValueError(f"no setting '{name}' (settings: {', '.join(sorted(allowed))})")


def parse(items: Iterable[str], allowed: Iterable[str] | None = None) -> dict[str, bool | int | float]:
    """Settings from NAME=VALUE strings, each value parsed by pydantic as its setting's type; a bad
    name or value is a ValueError naming it. ``allowed``: the names accepted (default: all)."""
    from pydantic import TypeAdapter, ValidationError

    table = registry()
    allowed = set(table if allowed is None else allowed)
    out: dict[str, bool | int | float] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep:
            raise ValueError(f"expected NAME=VALUE, got '{item}'")
        if name not in allowed:
            raise _unknown(name, allowed)
        kind = table[name].kind
        try:
            out[name] = TypeAdapter(kind).validate_python(text)
        except ValidationError:
            raise ValueError(f"{name}: expected a value of type {kind.__name__}, got '{text}'") from None
    return out


def split(values: Mapping[str, object]) -> tuple[dict[str, object], dict[str, object]]:
    """``values`` by dotted name parted into the tracker's and the physics' (``population.*``, by
    PopulationConfig's own field names); an unknown name is a ValueError."""
    table = registry()
    tracker, physics = {}, {}
    for name, value in values.items():
        if name not in table:
            raise _unknown(name, table)
        outer, _, inner = name.partition(".")
        if outer == "population":
            physics[inner] = value
        else:
            tracker[name] = value
    PopulationConfig(**physics)  # out-of-range physics fails here, with the field named
    return tracker, physics


def tracker_config(values: Mapping[str, object], base: TrackerConfig | None = None) -> TrackerConfig:
    """``base`` (default: the defaults) with the tracker settings ``values`` changed, by dotted
    name; each value converted to its setting's type and checked by its group (a ValueError names it)."""
    config, table = base or TrackerConfig(), registry()
    top: dict[str, object] = {}
    nested: dict[str, dict[str, object]] = {}
    for name, value in values.items():
        setting = table.get(name)
        if setting is None or name.startswith("population."):
            raise _unknown(name, [n for n in table if not n.startswith("population.")])
        outer, dot, inner = name.partition(".")
        converted = setting.kind(value)
        if dot:
            nested.setdefault(outer, {})[inner] = converted
        else:
            top[outer] = converted
    cost = nested.pop("cost", {})
    if cost:
        terms = {t: cost.pop(t) for t in list(cost) if t in TERM_NAMES}
        weights = config.cost.weights or WEIGHTS
        cost["weights"] = tuple(terms.get(t, w) for t, w in zip(TERM_NAMES, weights, strict=True))
        nested["cost"] = cost
    groups = {g: replace(getattr(config, g), **v) for g, v in nested.items()}
    return replace(config, **groups, **top)


UNCHECKED_PALM: dict[str, bool | int | float | str] = {"optimizer.until_felt": True}
"""The settings of a robot that carries objects on its palm and whose config gives no ``[tracker]``
table: its own truth has not said whether its sensing ranks the worlds' poses, and a palm-up hand
whose fingertips touch the object seldom or never ranks them by chance. Held open loop until the
robot first feels the object, such a hand tracks as one open-loop world while it does not, and a
hand that feels it within a second or two keeps the population's gain (docs/tracker-settings.md)."""


def _unchecked_palm(robot: RobotSpec) -> bool:
    """Whether ``robot`` carries objects on its palm and its config gives no ``[tracker]`` table."""
    # The procedural hand declares no palm to carry on: only a robot file's config does.
    return robot.tracker is None and getattr(robot, "carries_on_palm", False)


def robot_defaults(robot: RobotSpec) -> dict[str, object]:
    """The tracker settings ``robot``'s config gives its sessions (its ``[tracker]`` table, or
    :data:`UNCHECKED_PALM` for a palm-carrying robot without one) by dotted name, checked as a
    session's overrides are: a ValueError names the robot and the setting."""
    values = dict(UNCHECKED_PALM) if _unchecked_palm(robot) else dict(robot.tracker or ())
    try:
        tracker_config(values)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"robot '{robot.name}' tracker: {exc}") from None
    return values


def unchecked_palms(robots: Mapping[str, RobotSpec]) -> list[str]:
    """The names of ``robots`` that carry objects on their palm and whose config gives no
    ``[tracker]`` table: their sessions run :data:`UNCHECKED_PALM`, which on some palm-up hands (an
    object felt through its weight, or touched by a fingertip only in passing) can track worse than
    one open-loop world where that world starts close to the truth, and only the robot's own truth
    (``check-settings``) says which settings it needs."""
    return [name for name, spec in robots.items() if _unchecked_palm(spec)]


def changed(config: TrackerConfig, physics: Mapping[str, object] | None = None) -> dict[str, object]:
    """The settings of ``config`` (and the physics overrides ``physics``, by PopulationConfig's
    field names) that differ from the defaults, by dotted name: a run's record of what it changed."""
    default, table = TrackerConfig(), registry()
    out: dict[str, object] = {}
    for name in table:
        outer, dot, inner = name.partition(".")
        if outer == "population" or name == "seed":
            continue
        if outer == "cost" and inner in TERM_NAMES:
            i = TERM_NAMES.index(inner)
            now, was = (c.cost.weights[i] if c.cost.weights else None for c in (config, default))
        elif dot:
            now, was = getattr(getattr(config, outer), inner), getattr(getattr(default, outer), inner)
        else:
            now, was = getattr(config, name), getattr(default, name)
        if now != was:
            out[name] = now
    defaults = PopulationConfig()
    out |= {f"population.{k}": v for k, v in (physics or {}).items() if getattr(defaults, k) != v}
    return out
