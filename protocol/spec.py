"""The wire spec for implementers in other languages, generated from the messages themselves: a
JSON Schema per message, a field table per message (Markdown), and golden payloads (msgpack bytes
beside the values they carry, as JSON) that a C++ or Rust implementation can decode and encode
against. ``inhand-tracker spec`` writes them under docs/protocol; a test keeps them current."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from .codec import encode
from .messages import (
    PROTOCOL_VERSION,
    CloseSession,
    Error,
    ErrorCode,
    OpenSession,
    PoseObservation,
    RobotFrame,
    ServiceInfo,
    SessionInfo,
)
from .reports import Estimate, SessionStatus
from .ros2_records import RECORD_TYPES, msg_definition
from .sensing import SENSING

__all__ = ["MESSAGES", "examples", "plain", "schemas", "write_spec"]

MESSAGES: tuple[type[BaseModel], ...] = (
    ServiceInfo, OpenSession, SessionInfo, CloseSession, RobotFrame, PoseObservation, Estimate, SessionStatus, Error,
)  # fmt: skip
"""Every message of the protocol."""


def schemas() -> dict[str, dict]:
    """The JSON Schema of every message, by name."""
    out = {}
    for model in MESSAGES:
        schema = model.model_json_schema()
        schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
        schema["$id"] = f"inhand/v{PROTOCOL_VERSION}/{model.__name__}"
        out[model.__name__] = schema
    return out


def examples() -> dict[str, BaseModel]:
    """One message of every kind with every field set, fixed values: the golden payloads."""
    pose = np.array([0.012, -0.034, 0.156, 0.0, 0.0, 0.38268343, 0.9238795], np.float32)
    cov = np.diag(np.array([4e-6, 4e-6, 9e-6, 2.5e-3, 2.5e-3, 1e-2], np.float32))
    q = np.linspace(-0.2, 0.9, 22, dtype=np.float32)
    token = "5f2b9c0e7d1a4b3c8e6f0a9d2c4b7e1f"
    # Every sensing field, filled with fixed values: D = 22 joints, L = 4 sensors, Z = 3 touch zones.
    frame = {}
    for f in SENSING:
        shape = f.shape(len(q), 4, 3)
        frame[f.name] = np.linspace(-0.5, 0.5, int(np.prod(shape)), dtype=np.float32).reshape(shape)
    return {
        "ServiceInfo": ServiceInfo(
            name="default", device="cuda:0", robots=["allegro"], objects=["foam_brick", "spam_can"],
            methods=["OLP", "EYE", "WRS", "REPS", "PBO"], groups=8, max_worlds=65536, sessions=1, max_sessions=64,
            rate_hz=30.0, budget_ms=26.7, load_ms=14.2, free_worlds=512,
        ),
        "OpenSession": OpenSession(
            robot="allegro", object="foam_brick", p0=pose, q0=q, method="PBO", worlds=1024, allow_fewer=True,
            overrides={"update_every": 10.0}, name="left_hand",
        ),
        "SessionInfo": SessionInfo(
            session="3fa9c01b2d4e", token=token, robot="allegro", object="foam_brick",
            joint_names=[f"joint_{i}" for i in range(22)], sensor_names=["index", "middle", "ring", "thumb"],
            worlds=512, method="PBO", notice="worlds: 1024 do not fit the frame budget; granted 512",
            zone_names=["palm", "index_proximal", "thumb_proximal"], name="left_hand",
        ),
        "CloseSession": CloseSession(session="3fa9c01b2d4e", token=token),
        "RobotFrame": RobotFrame(session="3fa9c01b2d4e", seq=42, stamp=1.4, token=token, **frame),
        "PoseObservation": PoseObservation(session="3fa9c01b2d4e", token=token, stamp=1.4, pose=pose, covariance=cov),
        "Estimate": Estimate(
            session="3fa9c01b2d4e", seq=42, stamp=1.4, pose=pose, mean_pose=pose, covariance=cov, cost=0.125,
            mass=0.03, friction=0.8, status="ambiguous", modes=np.stack([pose, pose]),
            mode_weights=np.array([0.625, 0.375], np.float32), evidence=0.75, dead_reckoning=0.25, latency_ms=12.5,
            notice=None,
        ),
        "SessionStatus": SessionStatus(
            session="3fa9c01b2d4e", frames=43, gaps=0, duplicates=1, late=0, errors=1, stale=0, resyncs=0,
            latency_p50_ms=11.5, latency_p99_ms=19.25, cost=0.125, spread_m=0.004,
            last_error="RobotFrame.q: expected shape (22,), got (21,) (seq 17)", observations=2,
            observations_stale=0, reseeds_by_observation=0, budget_ms=26.7, load_ms=14.2, evidence=0.75,
            residuals={"joints": 0.004, "force": 0.25},
        ),
        "Error": Error(code=ErrorCode.CAPACITY, message="worlds: at most 512 fit now", others=["gpu1"]),
    }  # fmt: skip


def plain(message: BaseModel) -> dict:
    """A message's values as JSON: arrays as {dtype, shape, values}."""

    def value(v):
        if isinstance(v, np.ndarray):
            return {"dtype": v.dtype.str, "shape": list(v.shape), "values": v.ravel().tolist()}
        return v

    return {k: value(v) for k, v in message.model_dump(mode="python").items()}


def _table(name: str, schema: dict) -> str:
    required = set(schema.get("required", []))
    lines = [f"## {name}", "", " ".join(schema.get("description", "").split()), ""]
    lines += ["| field | type | required | meaning |", "|---|---|---|---|"]
    for field, spec in schema["properties"].items():
        kinds = [s for s in spec.get("anyOf", [spec])]
        kind = " or ".join(_kind(s) for s in kinds)
        text = " ".join(spec.get("description", "").split()).replace("|", "\\|")
        lines.append(f"| `{field}` | {kind} | {'yes' if field in required else 'no'} | {text} |")
    return "\n".join(lines) + "\n"


def _kind(spec: dict) -> str:
    if spec.get("properties", {}).get("__nd__"):
        return "float32 array (" + ", ".join(map(str, spec["x-shape"])) + ")"
    if "enum" in spec:
        return "one of " + ", ".join(f"`{v}`" for v in spec["enum"])
    if "const" in spec:
        return f"`{spec['const']}`"
    if spec.get("type") == "array":
        return f"list of {_kind(spec.get('items', {}))}"
    if spec.get("type") == "object":
        return "map of string to " + _kind(spec.get("additionalProperties", {}))
    if "$ref" in spec:
        return spec["$ref"].rsplit("/", 1)[-1]
    return {"integer": "int", "number": "float", "string": "str", "boolean": "bool", "null": "nil"}.get(
        spec.get("type", ""), "any"
    )


def write_spec(folder: str | Path) -> list[Path]:
    """Write ``schema/NAME.json``, ``golden/NAME.msgpack`` with ``golden/NAME.json``,
    ``ros2/msg/NAME.msg`` (the recordings' message types) and ``messages.md`` under ``folder``; the
    paths written."""
    folder = Path(folder)
    written = []
    all_schemas = schemas()
    for sub in ("schema", "golden", "ros2/msg"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    for model, name in RECORD_TYPES.values():
        path = folder / "ros2" / "msg" / f"{name.rsplit('/', 1)[-1]}.msg"
        path.write_text(msg_definition(model))
        written.append(path)
    for name, schema in all_schemas.items():
        path = folder / "schema" / f"{name}.json"
        path.write_text(json.dumps(schema, indent=2) + "\n")
        written.append(path)
    for name, message in examples().items():
        payload = encode(message)
        (folder / "golden" / f"{name}.msgpack").write_bytes(payload)
        (folder / "golden" / f"{name}.json").write_text(json.dumps(plain(message), indent=2) + "\n")
        written += [folder / "golden" / f"{name}.msgpack", folder / "golden" / f"{name}.json"]
    head = [
        f"# Messages of protocol v{PROTOCOL_VERSION}",
        "",
        "Generated by `inhand-tracker spec` from the message classes; see [the protocol](../protocol.md) for",
        'keys, encodings and errors. Arrays are the codec\'s map `{__nd__: true, dtype: "<f4", shape: [...],',
        "data: bin}`; units are in each field's meaning.",
        "",
        "",
    ]
    path = folder / "messages.md"
    path.write_text("\n".join(head) + "\n".join(_table(n, s) for n, s in all_schemas.items()))
    return [*written, path]
