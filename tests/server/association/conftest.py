"""Fixtures and helpers of the association tests: synthetic object measurements (known ground
truth, no images; built by tests/factories.py) and a run of the server's mapping stage over them."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from factories import CAMERA

from wardmap.server.association.associator import AssociationConfig
from wardmap.server.association.types import Landmark
from wardmap.server.mapping import MappedKeyframe, MapWriter
from wardmap.server.objectmap import ObjectMap
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store import MapStore

Scene = Sequence[tuple[Sequence[ObjectMeasurement], np.ndarray]]
"""Per keyframe: its measurements and T_world_camera (4, 4), in keyframe order."""


def map_scene(store: MapStore, scene: Scene, association: AssociationConfig | None = None,
              ) -> tuple[list[Landmark], ObjectMap, set[tuple[int, str]]]:
    """Run the server's map writer over ``scene`` as session r1/s1 seen by
    :data:`factories.CAMERA`, then close the session. Returns the associator's landmarks, the
    object map and every (object id, category) the map held after some keyframe, confirmed or not.
    """
    objects = ObjectMap(store)
    writer = MapWriter(objects, association)
    seen: set[tuple[int, str]] = set()
    for ms, T in scene:
        writer.add([MappedKeyframe("r1/s1", T, CAMERA, list(ms))])
        page = objects.query(include_unconfirmed=True)
        seen |= {(h.record.object_id, h.record.category) for h in page.hits}
    writer.close(["r1/s1"])
    return writer.landmarks(), objects, seen


def observation_counts(store: MapStore) -> dict[int, int]:
    """Stored observations per object id, orphans (of deleted objects) included."""
    return store.observation_counts()
