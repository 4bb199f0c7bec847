"""What a robot senses in one control frame, declared once.

Every form a frame takes is derived from :data:`SENSING`: the wire message
(:class:`protocol.RobotFrame`), the ``.traj`` file's ``frames`` table, the tracker's frame and
the packed row the GPU reads. A field is per joint (D of them), per fingertip sensor (L of them)
or per touch zone (Z of them: a scalar normal force on a region of a link, the way touch arrays,
pressure pads and taxel skins report), with a trailing shape. Optional fields come in presence
groups: a frame either carries a group (fingertip forces; translational slip; rotational slip;
touch zones) or not, and the tracker's cost drops the terms of a group the frame lacks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = ["PRESENCE", "SENSING", "SensingAttributes", "SensingField", "check_sensing", "sensing_field"]


@dataclass(frozen=True)
class SensingField:
    """One field of the robot's sensing record."""

    name: str
    per: Literal["joint", "sensor", "zone"]
    """What the leading axis counts: D actuated joints, L fingertip sensors or Z touch zones."""
    trailing: tuple[int, ...]
    """Shape per joint or sensor: () for a scalar, (3,) for a vector."""
    unit: str
    doc: str
    group: str | None = None
    """Presence group of an optional field; None for a field every frame carries."""
    bounds: tuple[float, float] | None = None
    """The values a real sensor reports (a service refuses others); None: per joint, the robot's
    limits decide."""

    def shape(self, d: int, l: int, z: int = 0) -> tuple[int, ...]:
        """The field's shape in one frame of a robot with ``d`` joints, ``l`` sensors and ``z`` zones."""
        return ({"joint": d, "sensor": l, "zone": z}[self.per], *self.trailing)

    @property
    def optional(self) -> bool:
        return self.group is not None


_FORCE = (-1e4, 1e4)  # [N]: more than any hand feels
_FLAG = (0.0, 1.0)
_UNIT = (-1.5, 1.5)  # a unit vector's components, with room for rounding

SENSING: tuple[SensingField, ...] = (
    SensingField(
        "controls",
        "joint",
        (),
        "rad or m",
        "Joint position targets, one per joint of the robot config in its order; a joint the robot's"
        " file does not drive (one a tendon ties to another) has its target ignored.",
    ),
    SensingField("q", "joint", (), "rad or m", "Measured joint positions."),
    SensingField(
        "force", "sensor", (3,), "N", "Contact force on each fingertip pad, in the sensor frame.", "force", _FORCE
    ),
    SensingField("slip", "sensor", (), "1", "Translational slip flags, 1 slipping, else 0.", "slip", _FLAG),
    SensingField(
        "slip_dir", "sensor", (2,), "1", "Unit slip directions in the sensors' tangent planes (x, y).", "slip", _UNIT
    ),
    SensingField("spin", "sensor", (), "1", "Rotational slip flags, 1 spinning, else 0.", "spin", _FLAG),
    SensingField(
        "spin_sense",
        "sensor",
        (),
        "1",
        "Rotational slip senses: 1 counter-clockwise about the pad normal.",
        "spin",
        _FLAG,
    ),
    SensingField(
        "touch",
        "zone",
        (),
        "N",
        "Normal force on each touch zone (palm, phalanges, taxels), as the robot declares.",
        "touch",
        _FORCE,
    ),
)
"""The robot's sensing record, in wire and packing order. Sensor frames: z is the pad normal,
pointing at the object; x-y is the pad's tangent plane."""

PRESENCE: tuple[str, ...] = tuple(dict.fromkeys(f.group for f in SENSING if f.group))
"""The presence groups, in order: ("force", "slip", "spin", "touch")."""

_BY_NAME = {f.name: f for f in SENSING}


class SensingAttributes:
    """A record whose sensing fields live in its ``sensing`` dict and read and write as attributes
    (``rec.force``, ``rec.force = ...``): a field replaced this way is where every reader looks."""

    sensing: dict

    def __getattr__(self, name: str):
        sensing = self.__dict__.get("sensing", {})
        if name in sensing:
            return sensing[name]
        raise AttributeError(f"'{type(self).__name__}' object has no attribute '{name}'")

    def __setattr__(self, name: str, value) -> None:
        if name in _BY_NAME and "sensing" in self.__dict__:
            self.sensing[name] = value
        else:
            super().__setattr__(name, value)


def sensing_field(name: str) -> SensingField:
    """The field called ``name``; a ValueError lists the known names."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"sensing field: '{name}' is not one of {list(_BY_NAME)}") from None


def check_sensing(values: dict[str, np.ndarray | None], d: int, l: int, lead: tuple[int, ...] = (), z: int = 0) -> None:
    """Check a record's shapes against a robot of ``d`` joints, ``l`` sensors and ``z`` touch zones,
    with leading axes ``lead`` (frames, groups, ...); a ValueError names the field and both shapes."""
    for name, value in values.items():
        if value is None:
            if not sensing_field(name).optional:
                raise ValueError(f"{name}: required, got None")
            continue
        expected = (*lead, *sensing_field(name).shape(d, l, z))
        if np.shape(value) != expected:
            raise ValueError(f"{name}: expected shape {expected}, got {np.shape(value)}")
