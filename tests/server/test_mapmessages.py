"""Object-map records as map messages (``server/mapmessages.py``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from wardmap.server.mapmessages import map_object
from wardmap.server.objectmap import ObjectMap, ObjectQuery, ObjectState
from wardmap.server.store import MapStore, open_store
from wardmap.shared.mapwire import MapObject, ObjectsReply, decode_map_message, encode_map_message
from wardmap.shared.se3 import yaw_transform


@pytest.fixture
def store(tmp_path: Path) -> Iterator[MapStore]:
    with open_store(f"sqlite:///{tmp_path / 'map.db'}") as s:
        yield s


def test_stored_objects_become_the_same_messages_the_checks_would_make(store: MapStore) -> None:
    """Objects written through the object map (with and without colour, odd yaws and sizes) come
    back as messages equal, field for field and in type, to the ones the message's own checks
    build from the same values; and they survive the wire round trip unchanged."""
    om = ObjectMap(store)
    rng = np.random.default_rng(3)
    om.upsert([
        ObjectState(i + 1, str(rng.choice(["door", "bed", "chair"])), float(rng.uniform(0.1, 1.0)),
                    yaw_transform(*rng.uniform(-50, 50, 2), float(rng.uniform(-3.1, 3.1)),
                                  float(rng.uniform(0, 2))),
                    rng.uniform(0.05, 3.0, 3), None if i % 2 else tuple(rng.uniform(0, 255, 3)))
        for i in range(20)
    ])
    page = om.find(ObjectQuery(near=(0.0, 0.0, 0.0), include_unconfirmed=True, limit=100))
    assert len(page.hits) == 20
    for hit in page.hits:
        fast = map_object(hit.record, hit.distance_m)
        fields = {f.name: getattr(fast, f.name) for f in dataclasses.fields(MapObject)}
        checked = MapObject(**fields)
        assert fast == checked
        for name in fields:
            assert type(getattr(fast, name)) is type(getattr(checked, name)), name
    reply = ObjectsReply(tuple(map_object(h.record, h.distance_m) for h in page.hits), page.next_offset)
    assert decode_map_message(encode_map_message(reply)) == reply


def test_unknown_fields_are_refused() -> None:
    """The unchecked constructor still takes exactly the message's fields: none missing, none extra."""
    with pytest.raises((KeyError, TypeError)):
        MapObject.checked_elsewhere(object_id=1)
    fields = {f.name: None for f in dataclasses.fields(MapObject)}
    with pytest.raises(TypeError, match="colour"):
        MapObject.checked_elsewhere(**fields, colour=(1, 2, 3))
