"""The object map's messages (shared/mapwire.py): one object shape for REST and Zenoh, which
robots decode. Round trips, the old shape still read, and malformed input raising a WireError
that names the field."""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any

import msgpack
import numpy as np
import pytest

from wardmap.shared.errors import WireError
from wardmap.shared.mapwire import (
    OBJECTS_KEY,
    SCHEMA_ERROR,
    SCHEMA_OBJECTS,
    SCHEMA_UPDATE,
    UPDATES_KEY,
    VERSION,
    MapError,
    MapObject,
    MapUpdate,
    ObjectsReply,
    decode_map_message,
    encode_map_message,
    object_from_wire,
    object_to_wire,
)
from wardmap.shared.se3 import rotation_to_quat, yaw_transform

OBJECT_FIELDS = {
    "object_id", "category", "confidence", "position", "q_xyzw", "T_world_object", "yaw", "size",
    "bounds_min", "bounds_max", "color_rgb", "n_observations", "first_seen_s", "last_seen_s", "robots",
    "confirmed", "distance_m",
}
"""The documented fields of an object (docs/map_api.md, "Payloads")."""


def _object(object_id: int = 7, **kw: Any) -> MapObject:
    T = yaw_transform(1.5, -2.0, 0.3, 0.45)
    fields: dict[str, Any] = {
        "object_id": object_id, "category": "wheelchair", "confidence": 0.8,
        "position": tuple(T[:3, 3]), "q_xyzw": tuple(rotation_to_quat(T[:3, :3])), "yaw": 0.3,
        "size": (0.7, 0.6, 0.9), "bounds_min": (1.0, -2.5, 0.0), "bounds_max": (2.0, -1.5, 0.9),
        "color_rgb": (200.0, 30.5, 12.0), "n_observations": 4, "first_seen_s": 1.7e9,
        "last_seen_s": 1.7e9 + 5, "robots": ("r1", "r2"), "confirmed": True, "distance_m": 2.5,
    }
    fields.update(kw)
    return MapObject(**fields)


def _objects_payload(obj: dict[str, Any]) -> bytes:
    message = {"schema": SCHEMA_OBJECTS, "version": VERSION, "objects": [obj], "next_offset": None}
    return msgpack.packb(message)


def test_keys() -> None:
    assert OBJECTS_KEY == "wardmap/v1/map/objects" and UPDATES_KEY == "wardmap/v1/map/updates"


@pytest.mark.parametrize(
    "message",
    [
        ObjectsReply((_object(1), _object(2, color_rgb=None, distance_m=None, robots=())), next_offset=40),
        ObjectsReply((), None),
        MapUpdate("created", _object(3, distance_m=None)),
        MapUpdate("deleted", _object(4, confirmed=False), merged_into=3),
        MapError("radius needs near=x,y,z"),
    ],
    ids=["objects", "empty", "update", "merge", "error"],
)
def test_round_trip(message: Any) -> None:
    """Every message decodes to an equal message (floats exact, tuples for lists)."""
    assert decode_map_message(encode_map_message(message)) == message


def test_one_object_shape_with_the_pose_twice() -> None:
    """The object map has every documented field, absent values as nil; the pose is there flat
    (REST's ``position``, ``q_xyzw``) and as ``T_world_object`` (the wire pose form)."""
    obj = _object(color_rgb=None, distance_m=None)
    wire = object_to_wire(obj)
    assert set(wire) == OBJECT_FIELDS and {f.name for f in dataclasses.fields(MapObject)} < OBJECT_FIELDS
    assert wire["T_world_object"] == {"t": wire["position"], "q_xyzw": wire["q_xyzw"]}
    assert wire["color_rgb"] is None and wire["distance_m"] is None
    assert object_from_wire(wire) == obj
    np.testing.assert_allclose(obj.T_world_object, yaw_transform(1.5, -2.0, 0.3, 0.45), atol=1e-12)


def test_the_shape_before_colour_and_flat_pose_still_decodes() -> None:
    """A reply of a server that sent only ``T_world_object``, left out ``color_rgb``, ``distance_m``
    and ``merged_into`` decodes, with None for what was left out."""
    old = object_to_wire(_object())
    for key in ("position", "q_xyzw", "color_rgb", "distance_m"):
        del old[key]
    msg = decode_map_message(_objects_payload(old))
    assert isinstance(msg, ObjectsReply)
    assert msg.objects[0] == _object(color_rgb=None, distance_m=None)
    update = msgpack.packb({"schema": SCHEMA_UPDATE, "version": VERSION, "kind": "updated", "object": old})
    assert decode_map_message(update) == MapUpdate("updated", _object(color_rgb=None, distance_m=None))


_DELETE = object()


def _with(**changes: Any) -> dict[str, Any]:
    wire = object_to_wire(_object())
    for key, value in changes.items():
        if value is _DELETE:
            del wire[key]
        else:
            wire[key] = value
    return wire


@pytest.mark.parametrize(
    ("obj", "field"),
    [
        (_with(confidence=1.5), "objects[0].confidence"),
        (_with(confidence=True), "objects[0].confidence"),
        (_with(object_id=0), "objects[0].object_id"),
        (_with(category=""), "objects[0].category"),
        (_with(category=_DELETE), "objects[0].category"),
        (_with(size=[1.0, -0.1, 2.0]), "objects[0].size[1]"),
        (_with(bounds_min=[0.0, 0.0]), "objects[0].bounds_min"),
        (_with(color_rgb=[1.0, float("nan"), 2.0]), "objects[0].color_rgb[1]"),
        (_with(robots=["r1", 3]), "objects[0].robots[1]"),
        (_with(confirmed=1), "objects[0].confirmed"),
        (_with(distance_m=-1.0), "objects[0].distance_m"),
        (_with(colour=[1, 2, 3]), "objects[0].colour"),
        (_with(T_world_object={"t": [0, 0, 0], "q_xyzw": [0, 0, 0, 2]}, position=_DELETE, q_xyzw=_DELETE),
         "objects[0].T_world_object.q_xyzw"),
        (_with(T_world_object={"t": [0, 0], "q_xyzw": [0, 0, 0, 1]}), "objects[0].T_world_object.t"),
        (_with(T_world_object={"t": [0, 0, 0]}), "objects[0].T_world_object.q_xyzw"),
        (_with(position=[9.0, 9.0, 9.0]), "objects[0].position"),
        ("not a map", "objects[0]"),
    ],
)
def test_bad_object_fields_are_named(obj: Any, field: str) -> None:
    with pytest.raises(WireError) as info:
        decode_map_message(_objects_payload(obj))
    assert info.value.field == field


@pytest.mark.parametrize(
    ("message", "field"),
    [
        ({"schema": SCHEMA_UPDATE, "version": VERSION, "kind": "moved", "object": object_to_wire(_object())},
         "kind"),
        ({"schema": SCHEMA_UPDATE, "version": VERSION, "kind": "created", "object": object_to_wire(_object()),
          "merged_into": 2}, "merged_into"),
        ({"schema": SCHEMA_OBJECTS, "version": VERSION, "objects": [], "next_offset": -1}, "next_offset"),
        ({"schema": SCHEMA_OBJECTS, "version": VERSION, "objects": {}, "next_offset": None}, "objects"),
        ({"schema": SCHEMA_ERROR, "version": VERSION, "detail": ""}, "detail"),
        ({"schema": SCHEMA_ERROR, "version": VERSION}, "detail"),
        ({"schema": SCHEMA_ERROR, "version": VERSION, "detail": "x", "extra": 1}, "extra"),
        ({"schema": "other", "version": 1}, "schema"),
        ({"schema": SCHEMA_OBJECTS, "version": 99}, "version"),
        ({"schema": SCHEMA_OBJECTS, "version": True}, "version"),
    ],
)
def test_bad_message_fields_are_named(message: dict[str, Any], field: str) -> None:
    with pytest.raises(WireError) as info:
        decode_map_message(msgpack.packb(message))
    assert info.value.field == field


@pytest.mark.parametrize(
    ("payload", "match"),
    [
        (b"\xc1", "not a msgpack"),
        (msgpack.packb([1, 2]), "expected a map"),
        (msgpack.packb({"schema": "other", "version": 1}), "unknown map schema"),
        (msgpack.packb({"schema": SCHEMA_OBJECTS, "version": 99}), "unsupported version"),
    ],
    ids=["garbage", "list", "schema", "version"],
)
def test_bad_messages_are_wire_errors(payload: bytes, match: str) -> None:
    with pytest.raises(WireError, match=match):
        decode_map_message(payload)


def test_oversize_message_is_refused_before_unpacking() -> None:
    with pytest.raises(WireError, match="exceeds"):
        decode_map_message(b"\x00" * 101, max_bytes=100)


def test_messages_validate_on_construction() -> None:
    """A message that exists is valid: constructors raise WireError naming the field."""
    for kw, field in [({"confidence": -0.1}, "confidence"), ({"q_xyzw": (0.0, 0.0, 0.0, 0.5)}, "q_xyzw"),
                      ({"position": (0.0, float("inf"), 0.0)}, "position[1]"), ({"robots": "r1"}, "robots")]:
        with pytest.raises(WireError) as info:
            _object(**kw)
        assert info.value.field == field
    with pytest.raises(WireError, match="merged_into"):
        MapUpdate("updated", _object(), merged_into=2)
    with pytest.raises(WireError, match="detail"):
        MapError("")
    with pytest.raises(WireError, match="objects\\[0\\]"):
        ObjectsReply(("not an object",), None)  # type: ignore[arg-type]
    with pytest.raises(WireError, match="not a map message"):
        encode_map_message("hello")  # type: ignore[arg-type]


def test_fuzzed_payloads_raise_only_wire_errors() -> None:
    """Truncated, bit-flipped and spliced replies raise WireError and nothing else (seeded)."""
    rng = np.random.default_rng(5)
    good = encode_map_message(ObjectsReply((_object(1), _object(2, color_rgb=None)), next_offset=2))
    for _ in range(300):
        data = bytearray(good)
        kind = int(rng.integers(3))
        if kind == 0:
            data = data[: int(rng.integers(0, len(data)))]
        elif kind == 1:
            for pos in rng.integers(0, len(data), 3):
                data[int(pos)] ^= 1 << int(rng.integers(8))
        else:
            cut = int(rng.integers(0, len(data)))
            data = data[:cut] + rng.integers(0, 256, 8, dtype=np.uint8).tobytes() + data[cut:]
        with contextlib.suppress(WireError):
            decode_map_message(bytes(data))
