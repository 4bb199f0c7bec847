"""The protocol's records as ROS 2 messages of the package ``inhand_tracker``: each ``.msg``
definition derived from the record's own JSON Schema, and their CDR through rosbags' type store.
Session recordings carry them, so that every channel of a recording has a ROS 2 schema: tools
that read rosbag2's MCAP storage (rosbags) read it from the file's own schemas.

A field maps by its JSON type: string to ``string``, integer to ``int64``, number to ``float64``,
boolean to ``bool``; a float32 array to ``float32[]`` in C order (its leading length follows from
the trailing ones the schema fixes). A field that may be absent gets a ``bool has_<name>`` before
it, since ROS 2 fields cannot be null. Secrets (``token``, ``mac``) are never recorded.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from pydantic import BaseModel

from .messages import PoseObservation, RobotFrame
from .reports import Estimate, PopulationSummary

__all__ = ["RECORD_TYPES", "decode_record", "encode_record", "msg_definition", "typestore"]

PACKAGE = "inhand_tracker"
RECORD_TYPES: dict[str, tuple[type[BaseModel], str]] = {
    "frame": (RobotFrame, f"{PACKAGE}/msg/RobotFrame"),
    "observation": (PoseObservation, f"{PACKAGE}/msg/PoseObservation"),
    "estimate": (Estimate, f"{PACKAGE}/msg/Estimate"),
    "population": (PopulationSummary, f"{PACKAGE}/msg/PopulationSummary"),
}
"""Each recorded role's protocol model and its ROS 2 message type."""
_SECRET = frozenset({"token", "mac"})
_SCALARS = {"string": "string", "integer": "int64", "number": "float64", "boolean": "bool"}


@functools.cache
def _fields(model: type[BaseModel]) -> tuple[tuple[str, str, bool, tuple], ...]:
    """(name, ROS type, may be absent, trailing shape of an array) per recorded field of ``model``."""
    out = []
    for name, prop in model.model_json_schema()["properties"].items():
        if name in _SECRET:
            continue
        options = prop.get("anyOf", [prop])
        nullable = any(o.get("type") == "null" for o in options)
        (kind,) = [o for o in options if o.get("type") != "null"]
        if "x-shape" in kind:
            out.append((name, "float32[]", nullable, tuple(kind["x-shape"][1:])))
        elif kind.get("type") in _SCALARS:
            out.append((name, _SCALARS[kind["type"]], nullable, ()))
        else:
            raise TypeError(f"{model.__name__}.{name}: no ROS 2 field for the JSON Schema {kind}")
    return tuple(out)


def msg_definition(model: type[BaseModel]) -> str:
    """``model``'s ``.msg`` text, each field with what it is and its unit as a comment (the
    record's own description: ``[m]``, ``[rad]``, ``[s]``...), so that a recording says them."""
    about = " ".join((model.__doc__ or model.__name__).split()).split(". ")[0].rstrip(".")
    lines = [f"# {about}."]
    described = model.model_json_schema()["properties"]
    for name, ros, nullable, _ in _fields(model):
        if nullable:
            lines.append(f"bool has_{name}  # whether {name} is present")
        text = " ".join(described[name].get("description", "").split())
        lines.append(f"{ros} {name}" + (f"  # {text}" if text else ""))
    return "\n".join(lines) + "\n"


@functools.cache
def typestore():
    """rosbags' ROS 2 (Jazzy) type store with the protocol's records registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for model, name in RECORD_TYPES.values():
        store.register(get_types_from_msg(msg_definition(model), name))
    return store


def encode_record(role: str, record: BaseModel) -> bytes:
    """The CDR of ``record`` as its role's message."""
    model, name = RECORD_TYPES[role]
    values: dict[str, Any] = {}
    for field, ros, nullable, _ in _fields(model):
        value = getattr(record, field)
        if nullable:
            values[f"has_{field}"] = value is not None
        if ros == "float32[]":
            values[field] = np.zeros(0, np.float32) if value is None else np.asarray(value, np.float32).ravel()
        else:
            values[field] = value if value is not None else {"string": "", "bool": False}.get(ros, 0)
    store = typestore()
    return bytes(store.serialize_cdr(store.types[name](**values), name))


def decode_record(role: str, data: bytes) -> dict[str, Any]:
    """The fields of a role's message from its CDR: arrays in their shapes, absent ones None."""
    model, name = RECORD_TYPES[role]
    message = typestore().deserialize_cdr(data, name)
    out: dict[str, Any] = {}
    for field, ros, nullable, trailing in _fields(model):
        if nullable and not getattr(message, f"has_{field}"):
            out[field] = None
            continue
        value = getattr(message, field)
        out[field] = np.asarray(value, np.float32).reshape(-1, *trailing) if ros == "float32[]" else value
    return out
