"""Object-map records as the shared map messages (``shared/mapwire.py``).

The REST routes (``server/api/routes/objects.py``) and the Zenoh service
(``server/mapserve.py``) both build their objects here, so an object has one shape in both:
:class:`~wardmap.shared.mapwire.MapObject` (docs/map_api.md, "Payloads").
"""

from __future__ import annotations

from wardmap.server.objectmap import ObjectChange, ObjectPage, ObjectRecord
from wardmap.shared.mapwire import MapObject, MapUpdate, ObjectsReply

__all__ = ["map_object", "map_update", "objects_reply"]


def map_object(record: ObjectRecord, distance_m: float | None = None) -> MapObject:
    """The message of a stored object; ``distance_m`` from the query's ``near``, if any. The
    store checked every value when it was written (``ObjectMap.upsert``), so the message's
    checks are not run again (``MapObject.checked_elsewhere``)."""
    return MapObject.checked_elsewhere(
        object_id=record.object_id, category=record.category, confidence=record.confidence,
        position=record.position, q_xyzw=record.q_xyzw, yaw=record.yaw, size=record.size,
        bounds_min=record.bounds_min, bounds_max=record.bounds_max, color_rgb=record.color_rgb,
        n_observations=record.n_observations, first_seen_s=record.first_seen_s,
        last_seen_s=record.last_seen_s, robots=record.robots, confirmed=record.confirmed,
        distance_m=None if distance_m is None else float(distance_m),
    )


def objects_reply(page: ObjectPage) -> ObjectsReply:
    """One page of :meth:`ObjectMap.find` as the queryable's reply."""
    return ObjectsReply(tuple(map_object(h.record, h.distance_m) for h in page.hits), page.next_offset)


def map_update(change: ObjectChange) -> MapUpdate:
    """A committed change of the object map as one update message."""
    return MapUpdate(change.kind, map_object(change.record), change.merged_into)
