"""The object map's Zenoh message format (shared/mapwire.py), which robots decode."""

from __future__ import annotations

import msgpack
import pytest

from wardmap.shared.errors import WireError
from wardmap.shared.mapwire import (
    OBJECTS_KEY,
    SCHEMA_ERROR,
    SCHEMA_OBJECTS,
    UPDATES_KEY,
    VERSION,
    decode_map_message,
    pack_map_message,
)


def test_round_trip_and_keys() -> None:
    msg = decode_map_message(pack_map_message(SCHEMA_OBJECTS, {"objects": [], "next_offset": None}))
    assert msg == {"schema": SCHEMA_OBJECTS, "version": VERSION, "objects": [], "next_offset": None}
    err = decode_map_message(pack_map_message(SCHEMA_ERROR, {"detail": "bad radius"}))
    assert err["detail"] == "bad radius"
    assert OBJECTS_KEY == "wardmap/v1/map/objects" and UPDATES_KEY == "wardmap/v1/map/updates"
    with pytest.raises(ValueError, match="unknown map schema"):
        pack_map_message("wardmap.keyframe", {})


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
