"""Tests of wardmap.shared.robotwire (schema ``wardmap.correction``): round trips, every field
validated on decode and on construction, payload-level errors, and a seeded fuzz test."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
from factories import mutate, pack, random_pose

from wardmap.shared.errors import WireError
from wardmap.shared.robotwire import (
    CORRECTION_STATES,
    MAX_CORRECTION_BYTES,
    SCHEMA_CORRECTION,
    CorrectionMsg,
    decode_correction,
    encode_correction,
)
from wardmap.shared.se3 import yaw_transform
from wardmap.shared.wire import encode
from wardmap.shared.zenoh_config import ALL_CORRECTIONS, correction_key

T0 = 1_700_000_000.0
GOOD = CorrectionMsg("robot_0", "s1", 3, T0, yaw_transform(1.0, -2.0, 0.7, 0.1), anchored_to="robot_1/s0")


def _assert_equal(a: CorrectionMsg, b: CorrectionMsg) -> None:
    assert (a.robot_id, a.session_id, a.revision, a.stamp, a.state, a.anchored_to) == (
        b.robot_id, b.session_id, b.revision, b.stamp, b.state, b.anchored_to)
    np.testing.assert_allclose(a.T_map_odom, b.T_map_odom, atol=1e-12)


@pytest.mark.parametrize("anchored_to", [None, "robot_1/s0"])
def test_correction_round_trip(anchored_to: str | None) -> None:
    """50 random corrections, with and without ``anchored_to``, decode to equal messages (the pose
    to 1e-12: it travels as translation + quaternion); the optional field is omitted when absent."""
    rng = np.random.default_rng(0)
    for i in range(50):
        msg = CorrectionMsg(f"r{i}", "sess-1", i, T0 + i, random_pose(rng), "anchored", anchored_to)
        payload = encode_correction(msg)
        assert len(payload) < 300
        assert ("anchored_to" in msgpack.unpackb(payload)) == (anchored_to is not None)
        back = decode_correction(payload)
        _assert_equal(msg, back)
        assert not back.T_map_odom.flags.writeable


def test_keys() -> None:
    """The correction key lies in the server-owned subtree ``wardmap/v1/robots/<id>/``."""
    assert correction_key("r-1.a_b") == "wardmap/v1/robots/r-1.a_b/correction"
    assert ALL_CORRECTIONS == "wardmap/v1/robots/*/correction"
    assert CORRECTION_STATES == ("anchored",)


def _wire() -> dict[str, Any]:
    out: dict[str, Any] = msgpack.unpackb(encode_correction(GOOD), raw=False)
    return out


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], dict[str, Any]]:
    def edit(d: dict[str, Any]) -> dict[str, Any]:
        *parents, last = path.split(".")
        node = d
        for p in parents:
            node = node[p]
        node[last] = value
        return d
    return edit


def _delete(path: str) -> Callable[[dict[str, Any]], dict[str, Any]]:
    def edit(d: dict[str, Any]) -> dict[str, Any]:
        *parents, last = path.split(".")
        node = d
        for p in parents:
            node = node[p]
        del node[last]
        return d
    return edit


CASES: list[tuple[str, Callable[[dict[str, Any]], Any], str]] = [
    ("schema other", _set("schema", "wardmap.keyframe"), "schema"),
    ("schema missing", _delete("schema"), "schema"),
    ("version 2", _set("version", 2), "version"),
    ("version bool", _set("version", True), "version"),
    ("robot_id missing", _delete("robot_id"), "robot_id"),
    ("robot_id bad characters", _set("robot_id", "r 1"), "robot_id"),
    ("robot_id too long", _set("robot_id", "r" * 65), "robot_id"),
    ("session_id wrong type", _set("session_id", 5), "session_id"),
    ("session_id empty", _set("session_id", ""), "session_id"),
    ("revision negative", _set("revision", -1), "revision"),
    ("revision float", _set("revision", 1.0), "revision"),
    ("revision bool", _set("revision", True), "revision"),
    ("revision huge", _set("revision", 2**63), "revision"),
    ("revision missing", _delete("revision"), "revision"),
    ("stamp zero", _set("stamp", 0.0), "stamp"),
    ("stamp NaN", _set("stamp", math.nan), "stamp"),
    ("stamp inf", _set("stamp", math.inf), "stamp"),
    ("stamp string", _set("stamp", "1"), "stamp"),
    ("pose missing", _delete("T_map_odom"), "T_map_odom"),
    ("pose not a map", _set("T_map_odom", [1, 2]), "T_map_odom"),
    ("pose t NaN", _set("T_map_odom.t", [0.0, math.nan, 0.0]), "T_map_odom.t[1]"),
    ("pose t short", _set("T_map_odom.t", [0.0, 0.0]), "T_map_odom.t"),
    ("pose q not unit", _set("T_map_odom.q_xyzw", [0.0, 0.0, 0.0, 2.0]), "T_map_odom.q_xyzw"),
    ("pose q inf", _set("T_map_odom.q_xyzw", [0.0, 0.0, math.inf, 1.0]), "T_map_odom.q_xyzw[2]"),
    ("pose extra field", _set("T_map_odom.scale", 1.0), "T_map_odom.scale"),
    ("state unknown", _set("state", "lost"), "state"),
    ("state wrong type", _set("state", 1), "state"),
    ("state missing", _delete("state"), "state"),
    ("anchored_to no slash", _set("anchored_to", "robot_1"), "anchored_to"),
    ("anchored_to three parts", _set("anchored_to", "a/b/c"), "anchored_to"),
    ("anchored_to bad id", _set("anchored_to", "a/b c"), "anchored_to"),
    ("anchored_to wrong type", _set("anchored_to", 3), "anchored_to"),
    ("unknown field", _set("covariance", [1.0]), "covariance"),
    ("not a map", lambda d: [d], ""),
]


@pytest.mark.parametrize(("mutation", "field"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_invalid_correction_names_field(mutation: Callable[[dict[str, Any]], Any], field: str) -> None:
    """Each malformed variant of a valid correction raises WireError whose .field names it."""
    with pytest.raises(WireError) as e:
        decode_correction(pack(mutation(copy.deepcopy(_wire()))))
    assert e.value.field == field, str(e.value)


def test_anchored_to_nil_reads_as_absent() -> None:
    """``nil`` is read as an absent optional field, as in the keyframe schema."""
    assert decode_correction(pack(_set("anchored_to", None)(_wire()))).anchored_to is None


def test_payload_level_errors() -> None:
    """Oversize, truncated, garbage, non-bytes, ext types and another schema's message raise
    WireError; payload-level ones with the empty field."""
    good = encode_correction(GOOD)
    cases: list[Any] = [b"", good[:-3], b"\xc1", bytes(range(256)) * 20, "not bytes",
                        pack(msgpack.ExtType(5, b"abc")), pack({1: 2}), b"\x91" * 200 + b"\xc0",
                        bytes(MAX_CORRECTION_BYTES + 1)]
    for payload in cases:
        with pytest.raises(WireError) as e:
            decode_correction(payload)
        assert e.value.field == "", (payload[:20], str(e.value))
    with pytest.raises(WireError) as e:
        decode_correction(good, max_bytes=len(good) - 1)
    assert e.value.field == "" and "exceeds" in str(e.value)
    from wardmap.shared.wire import AckMsg

    with pytest.raises(WireError) as e:
        decode_correction(encode(AckMsg("robot_0", "s1", 0, "stored")))
    assert e.value.field == "schema"


def test_constructor_validates() -> None:
    """A CorrectionMsg validates on construction, naming the field; nothing else encodes."""
    pose = np.eye(4)
    cases: list[tuple[Callable[[], object], str]] = [
        (lambda: CorrectionMsg("r 1", "s", 0, T0, pose), "robot_id"),
        (lambda: CorrectionMsg("r", "", 0, T0, pose), "session_id"),
        (lambda: CorrectionMsg("r", "s", -1, T0, pose), "revision"),
        (lambda: CorrectionMsg("r", "s", True, T0, pose), "revision"),
        (lambda: CorrectionMsg("r", "s", 0, math.nan, pose), "stamp"),
        (lambda: CorrectionMsg("r", "s", 0, T0, np.eye(4) * 2), "T_map_odom"),
        (lambda: CorrectionMsg("r", "s", 0, T0, np.eye(3)), "T_map_odom"),
        (lambda: CorrectionMsg("r", "s", 0, T0, np.full((4, 4), np.nan)), "T_map_odom"),
        (lambda: CorrectionMsg("r", "s", 0, T0, pose, "lost"), "state"),
        (lambda: CorrectionMsg("r", "s", 0, T0, pose, anchored_to="x"), "anchored_to"),
    ]
    for build, field in cases:
        with pytest.raises(WireError) as e:
            build()
        assert e.value.field == field, str(e.value)
    with pytest.raises(WireError):
        encode_correction("not a message")
    assert msgpack.unpackb(encode_correction(GOOD))["schema"] == SCHEMA_CORRECTION


def test_fuzz_decode_raises_only_wire_errors() -> None:
    """500 seeded random mutations (bit flips, truncations, insertions, random payloads, structural
    edits of the decoded tree) of valid corrections: decode returns a valid message or raises
    WireError -- never another exception."""
    rng = np.random.default_rng(11)
    bases = [encode_correction(GOOD), encode_correction(CorrectionMsg("r", "s", 0, T0, np.eye(4)))]
    outcomes = {"ok": 0, "wire_error": 0}
    for trial in range(500):
        payload = mutate(bases[trial % len(bases)], rng, random_payloads=True)
        try:
            msg = decode_correction(payload)
        except WireError:
            outcomes["wire_error"] += 1
            continue
        except Exception as exc:  # the property under test
            pytest.fail(f"trial {trial}: {type(exc).__name__}: {exc}")
        assert isinstance(msg, CorrectionMsg) and np.isfinite(msg.T_map_odom).all()
        outcomes["ok"] += 1
    assert outcomes["wire_error"] > 250
