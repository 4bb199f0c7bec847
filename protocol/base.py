"""What every message of the protocol shares: strict, frozen pydantic models whose field
docstrings are the wire spec's descriptions."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

__all__ = ["WireMessage"]


class WireMessage(BaseModel):
    """A message on the wire: a field of the wrong type is refused, not coerced; unknown fields too."""

    # Field docstrings become the JSON Schema's descriptions (docs/protocol). Strict: a wire value
    # of the wrong type ("3" for a protocol version, "yes" for a flag) is refused, not coerced.
    model_config = ConfigDict(
        arbitrary_types_allowed=True, frozen=True, extra="forbid", use_attribute_docstrings=True, strict=True
    )
