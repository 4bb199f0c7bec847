"""The wire protocol: round trips, refusals that name the field and the numbers, no pickle, and
a light import."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest

from inhand_tracker.protocol import (
    MAX_PAYLOAD_BYTES,
    PROTOCOL_VERSION,
    DecodeError,
    Error,
    ErrorCode,
    Estimate,
    Keys,
    OpenSession,
    RobotFrame,
    check_version,
    decode,
    encode,
)

POSE = [0.1, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0]


def _frame(**kw) -> RobotFrame:
    fields = dict(session="s1", seq=3, stamp=1.5, controls=np.zeros(22), q=np.ones(22), force=np.zeros((4, 3)))
    return RobotFrame(**(fields | kw))


def test_messages_round_trip_with_arrays_intact():
    frame = _frame(slip=np.array([0, 1, 0, 0]), slip_dir=np.zeros((4, 2)))
    back = decode(encode(frame), RobotFrame)
    assert back.seq == 3 and back.q.dtype == np.float32 and np.array_equal(back.q, np.ones(22))
    assert back.force.shape == (4, 3) and back.spin is None
    est = Estimate(session="s1", seq=3, stamp=1.5, pose=POSE, mean_pose=POSE, covariance=np.eye(6) * 1e-6,
                   cost=1.2, mass=0.03, friction=0.9, status="tracking", latency_ms=4.0)  # fmt: skip
    assert decode(encode(est), Estimate).covariance.shape == (6, 6)
    err = decode(encode(Error(code=ErrorCode.UNKNOWN_OBJECT, message="object: 'duck'")), Error)
    assert err.code is ErrorCode.UNKNOWN_OBJECT


def test_bad_values_are_refused_naming_the_field_and_the_numbers():
    with pytest.raises(ValueError, match=r"(?s)controls.*1 non-finite values, first at \(5,\) = nan"):
        _frame(controls=np.where(np.arange(22) == 5, np.nan, 0.0))
    with pytest.raises(ValueError, match=r"(?s)force.*expected last dimension 3, got shape \(4, 2\)"):
        _frame(force=np.zeros((4, 2)))
    with pytest.raises(ValueError, match="seq"):
        _frame(seq=-1)
    with pytest.raises(ValueError, match=r"(?s)p0.*expected last dimension 7"):
        OpenSession(robot="allegro", object="foam_brick", p0=[0.0] * 6)
    # A peer that skips validation still cannot slip NaN past decode.
    raw = encode(_frame()).replace(np.float32(1.0).tobytes(), np.float32(np.inf).tobytes(), 1)
    with pytest.raises(DecodeError, match=r"RobotFrame\.q: 1 non-finite values, first at \(0,\) = inf"):
        decode(raw, RobotFrame)


def test_malformed_oversized_and_pickled_payloads_are_refused():
    with pytest.raises(DecodeError, match="payload: not valid msgpack"):
        decode(b"\xc1\x00\xff", RobotFrame)
    with pytest.raises(DecodeError, match=f"payload: {MAX_PAYLOAD_BYTES + 1} bytes exceeds the limit of"):
        decode(b"\x00" * (MAX_PAYLOAD_BYTES + 1), RobotFrame)
    with pytest.raises(DecodeError, match="payload: expected a map, got list"):
        decode(msgpack.packb([1, 2]), RobotFrame)
    evil = msgpack.packb({"__nd__": True, "dtype": "|O", "shape": [1], "data": b"\x80\x04."})
    with pytest.raises(DecodeError, match=r"array dtype: '\|O' is not allowed"):
        decode(evil, RobotFrame)
    short = msgpack.packb({"__nd__": True, "dtype": "<f4", "shape": [22], "data": b"\x00" * 8})
    with pytest.raises(DecodeError, match=r"array data: shape \[22\] of <f4 needs 88 bytes, got 8"):
        decode(short, RobotFrame)
    with pytest.raises(DecodeError, match=r"RobotFrame\.bogus: Extra inputs are not permitted"):
        decode(msgpack.packb(msgpack.unpackb(encode(_frame())) | {"bogus": 1}), RobotFrame)


def test_version_mismatch_names_both_versions():
    check_version(PROTOCOL_VERSION)
    newer = PROTOCOL_VERSION + 1
    with pytest.raises(ValueError, match=f"client speaks v{newer}, service speaks v{PROTOCOL_VERSION}"):
        check_version(newer)


def test_keys_live_under_the_versioned_prefix_and_refuse_bad_names():
    keys = Keys("lab-1")
    assert keys.frame("s1") == "inhand/v7/lab-1/s/s1/frame"
    assert keys.open == "inhand/v7/lab-1/rpc/open" and keys.alive == "inhand/v7/lab-1/alive"
    for bad in ("a/b", "*", "", "x y"):
        with pytest.raises(ValueError, match="session name: expected 1-64 characters"):
            keys.pose(bad)


def test_protocol_imports_stay_light():
    code = (
        "import sys, inhand_tracker.protocol;"
        " bad = {'torch', 'warp', 'newton', 'trimesh'} & set(sys.modules); print(sorted(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_the_committed_wire_spec_is_current(tmp_path):
    """docs/protocol is what `inhand-tracker spec` writes from the messages today."""
    from inhand_tracker.protocol.spec import write_spec

    docs = Path(__file__).resolve().parents[1] / "docs" / "protocol"
    for path in write_spec(tmp_path):
        committed = docs / path.relative_to(tmp_path)
        assert committed.exists() and committed.read_bytes() == path.read_bytes(), (
            f"{committed} is stale: run `inhand-tracker spec`"
        )


def test_golden_payloads_decode_to_their_values_and_encode_to_their_bytes():
    """What an implementer in another language checks theirs against."""
    import json

    from inhand_tracker import protocol
    from inhand_tracker.protocol.spec import MESSAGES, plain

    golden = Path(__file__).resolve().parents[1] / "docs" / "protocol" / "golden"
    assert sorted(p.stem for p in golden.glob("*.msgpack")) == sorted(m.__name__ for m in MESSAGES)
    for model in MESSAGES:
        payload = (golden / f"{model.__name__}.msgpack").read_bytes()
        values = json.loads((golden / f"{model.__name__}.json").read_text())
        message = decode(payload, getattr(protocol, model.__name__))
        assert plain(message) == values, model.__name__
        rebuilt = {
            k: np.asarray(v["values"], v["dtype"]).reshape(v["shape"]) if isinstance(v, dict) and "dtype" in v else v
            for k, v in values.items()
        }
        assert encode(model(**rebuilt)) == payload, model.__name__


def test_wire_values_of_the_wrong_type_are_refused_not_coerced():
    """A string where a number or a flag belongs is a client's bug: it is named, never guessed."""
    import msgpack

    from inhand_tracker.protocol import OpenSession, RobotFrame
    from inhand_tracker.protocol.codec import DecodeError, decode

    good = {"robot": "allegro", "object": "foam_brick", "p0": [0.1, 0.0, 0.05, 0.0, 0.0, 0.0, 1.0]}
    for field, value in (("protocol", "3"), ("allow_fewer", "yes"), ("worlds", 40.0)):
        with pytest.raises(DecodeError, match=f"OpenSession.{field}"):
            decode(msgpack.packb({**good, field: value}), OpenSession)
    with pytest.raises(DecodeError, match=r"RobotFrame\.seq"):
        decode(msgpack.packb({"session": "s", "seq": "5", "stamp": 0.0}), RobotFrame)
    with pytest.raises(DecodeError, match="valid msgpack but not a message"):
        decode(msgpack.packb({1: 2}), OpenSession)
    with pytest.raises(DecodeError, match="not valid msgpack"):
        decode(b"\xc1", OpenSession)


def test_a_message_built_with_bad_values_is_refused_in_one_line_naming_the_field_and_the_value():
    """What a user passes to open_session (or a config): no pydantic dump of every union branch."""
    from inhand_tracker.protocol import OpenSession, checked

    p0 = np.array([0, 0, 0.1, 0, 0, 0, 1.0])
    cases = [
        ({"worlds": 100000}, "OpenSession.worlds: Input should be less than or equal to 65536, got 100000"),
        (
            {"name": "left hand"},
            "OpenSession.name: 'left hand' is not a ROS 2 name: letters, digits and _, each part starting with a"
            " letter, parts joined by / (as in lab2/left_hand)",
        ),
        ({"p0": np.zeros(3)}, "OpenSession.p0: expected last dimension 7, got shape (3,)"),
        (
            {"client_key": "QUJD"},
            "OpenSession.client_key: expected an X25519 public key, 32 bytes in base64, got 3 bytes",
        ),
    ]
    for fields, said in cases:
        with pytest.raises(ValueError) as exc:
            checked(OpenSession, **({"robot": "allegro", "object": "foam_brick", "p0": p0} | fields))
        assert str(exc.value) == said and "\n" not in str(exc.value)
