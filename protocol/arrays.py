"""Array fields of the protocol's messages: float32 arrays of a rank (and a last dimension), finite,
carried as the codec's array map, with the JSON Schema that says so."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BeforeValidator, PlainSerializer, WithJsonSchema

__all__ = ["Matrix6", "Pose", "Poses", "Vec2s", "Vec3s", "Vector", "array_field"]


def array_field(rank: int, last: int | None = None):
    """A float32 array field of ``rank`` dimensions (the last ``last`` long), refused non-finite."""

    def convert(value):
        try:
            arr = np.asarray(value, dtype=np.float32)
        except (TypeError, ValueError):  # a map, a string, ragged lists: say what came
            raise ValueError(f"expected an array of numbers, got {type(value).__name__}") from None
        if arr.ndim != rank:
            raise ValueError(f"expected {rank} dimensions, got shape {arr.shape}")
        if last is not None and arr.shape[-1] != last:
            raise ValueError(f"expected last dimension {last}, got shape {arr.shape}")
        bad = ~np.isfinite(arr)
        if bad.any():
            index = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValueError(f"{int(bad.sum())} non-finite values, first at {index} = {arr[index]}")
        return arr

    shape = ["N"] * (rank - (last is not None)) + ([last] if last is not None else [])
    # On the wire an array is the codec's map (protocol/codec.py); msgpack's bin has no JSON type.
    schema = {
        "type": "object",
        "description": f"float32 array of shape ({', '.join(map(str, shape))}): the codec's array map",
        "x-shape": shape,
        "properties": {
            "__nd__": {"const": True},
            "dtype": {"const": "<f4"},
            "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": rank, "maxItems": rank},
            "data": {"description": "msgpack bin: the values, little-endian float32, C order"},
        },
        "required": ["__nd__", "dtype", "shape", "data"],
    }
    return Annotated[
        np.ndarray,
        BeforeValidator(convert),
        PlainSerializer(lambda a: a, return_type=np.ndarray),
        WithJsonSchema(schema),
    ]


Vector = array_field(1)
Pose = array_field(1, 7)
Vec3s = array_field(2, 3)
Poses = array_field(2, 7)
Vec2s = array_field(2, 2)
Matrix6 = array_field(2, 6)
