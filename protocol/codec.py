"""A msgpack codec for the protocol's messages: numpy arrays travel as {dtype, shape, bytes}
maps, never pickled; payloads and arrays have size limits."""

from __future__ import annotations

from typing import Any, TypeVar

import msgpack
import numpy as np
from pydantic import BaseModel, ValidationError

from .messages import PROTOCOL_VERSION

__all__ = [
    "MAX_ARRAY_BYTES",
    "MAX_PAYLOAD_BYTES",
    "MEDIA_TYPE",
    "DecodeError",
    "checked",
    "decode",
    "encode",
    "encoding_of",
    "pack_value",
    "unpack_array",
]

MAX_PAYLOAD_BYTES = 1 << 20
"""Largest message accepted [bytes]."""
MAX_ARRAY_BYTES = 1 << 18
"""Largest single array accepted [bytes]."""
_ARRAY_TAG = "__nd__"
_DTYPES = {"<f4", "<f8", "<i4", "<i8", "|u1", "|b1"}

M = TypeVar("M", bound=BaseModel)
MEDIA_TYPE = "application/msgpack"


def encoding_of(model: type[BaseModel]) -> str:
    """The Zenoh encoding every sample and reply of ``model`` carries: msgpack, with the message's
    name and protocol version as its schema (``application/msgpack;inhand.v7.Estimate``)."""
    return f"{MEDIA_TYPE};inhand.v{PROTOCOL_VERSION}.{model.__name__}"


class DecodeError(ValueError):
    """A payload that is not a valid message; the text names the field and the numbers."""


def pack_value(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        if value.dtype.str not in _DTYPES:
            raise TypeError(f"array dtype {value.dtype} is not sendable (allowed: {sorted(_DTYPES)})")
        return {_ARRAY_TAG: True, "dtype": value.dtype.str, "shape": list(value.shape), "data": value.tobytes()}
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot encode {type(value).__name__}")


def unpack_array(obj: dict, max_bytes: int = MAX_ARRAY_BYTES) -> Any:
    if obj.get(_ARRAY_TAG) is not True:
        return obj
    dtype, shape, data = obj.get("dtype"), obj.get("shape"), obj.get("data")
    if dtype not in _DTYPES:
        raise DecodeError(f"array dtype: {dtype!r} is not allowed (allowed: {sorted(_DTYPES)})")
    if not isinstance(shape, list) or not all(isinstance(n, int) and n >= 0 for n in shape) or len(shape) > 4:
        raise DecodeError(f"array shape: expected up to 4 non-negative integers, got {shape!r}")
    if not isinstance(data, bytes) or len(data) > max_bytes:
        size = len(data) if isinstance(data, bytes) else type(data).__name__
        raise DecodeError(f"array data: expected at most {max_bytes} bytes, got {size}")
    expected = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
    if len(data) != expected:
        raise DecodeError(f"array data: shape {shape} of {dtype} needs {expected} bytes, got {len(data)}")
    return np.frombuffer(data, dtype=dtype).reshape(shape).copy()


def encode(message: BaseModel) -> bytes:
    """msgpack bytes of ``message``."""
    return msgpack.packb(message.model_dump(), default=pack_value, use_bin_type=True)


def decode(payload: bytes, model: type[M]) -> M:
    """The ``model`` message in ``payload``, validated; DecodeError names what is wrong."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise DecodeError(f"payload: {len(payload)} bytes exceeds the limit of {MAX_PAYLOAD_BYTES}")
    try:
        raw = msgpack.unpackb(payload, object_hook=unpack_array, raw=False, strict_map_key=True)
    except DecodeError:
        raise
    except (msgpack.exceptions.UnpackException, msgpack.exceptions.ExtraData) as exc:  # malformed bytes
        raise DecodeError(f"payload: not valid msgpack ({type(exc).__name__}: {exc})") from exc
    except Exception as exc:  # well-formed msgpack that no message is: a map with non-string keys, ...
        raise DecodeError(f"payload: valid msgpack but not a message ({type(exc).__name__}: {exc})") from exc
    if not isinstance(raw, dict):
        raise DecodeError(f"payload: expected a map, got {type(raw).__name__}")
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        raise DecodeError(_one_line(model, exc)) from exc


def checked(model: type[M], **fields: Any) -> M:
    """The ``model`` message of ``fields``; a ValueError in one line names the field, what is
    wrong and the value given (pydantic's own lists every branch of a union over many lines)."""
    try:
        return model(**fields)
    except ValidationError as exc:
        raise ValueError(_one_line(model, exc, with_input=True)) from None


def _one_line(model: type[BaseModel], exc: ValidationError, with_input: bool = False) -> str:
    first = exc.errors()[0]
    # A union's branch (``constrained-int``, ``literal['auto']``) is pydantic's, not a field.
    where = ".".join(str(p) for p in first["loc"] if not (isinstance(p, str) and set(p) & set("-[("))) or model.__name__
    own = first["type"] == "value_error"  # a check of ours, whose message names the value itself
    given = f", got {first['input']!r}" if with_input and not own and "input" in first else ""
    return f"{model.__name__}.{where}: {first['msg'].removeprefix('Value error, ')}{given}"
