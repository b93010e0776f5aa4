"""The object map and robot trajectories as GeoJSON (RFC 7946) FeatureCollections.

Used by ``GET /v1/objects?format=geojson`` and ``wardmap export --format geojson``, so both
write the same features.

Coordinates are **map-frame metres** ``[x, y, z]`` (x, y on the floor, z up; the server's
shared map frame, docs/map_api.md), not WGS84 longitude and latitude: RFC 7946 sec. 4 allows
another reference system by prior arrangement, and the collection names it in its foreign
member ``wardmap`` (``{"frame": "map", "units": "m"}``). GIS tools that assume degrees will
draw the map at the wrong place and scale, but its shape is right.

- an object: a ``Point`` at its box centre; ``id`` its ``object_id``; ``properties`` the map
  object of the REST API (``shared/mapwire.py``: category, confidence, size, yaw, colour,
  first/last seen, robots, ...) without ``position`` and ``T_world_object``, which the
  geometry holds.
- a trajectory: a ``LineString`` of a robot's keyframe camera positions in time order;
  ``properties`` ``{"robot_id", "kind": "trajectory", "stamps": [s, ...]}``. A trajectory of one
  keyframe is a ``Point`` (a LineString needs two positions).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike

from wardmap.shared.mapwire import MapObject, object_to_wire

__all__ = ["FRAME_MEMBER", "MEDIA_TYPE", "feature_collection", "object_feature", "trajectory_feature"]

MEDIA_TYPE: Final = "application/geo+json"
"""The GeoJSON media type (RFC 7946 sec. 12)."""
FRAME_MEMBER: Final = {"frame": "map", "units": "m"}
"""The collection's ``wardmap`` foreign member: what the coordinates are."""

_IN_GEOMETRY: Final = ("position", "T_world_object")


def object_feature(obj: MapObject) -> dict[str, Any]:
    """A map object as a Point feature at its box centre (map frame, metres)."""
    props = {k: v for k, v in object_to_wire(obj).items() if k not in _IN_GEOMETRY}
    return {
        "type": "Feature",
        "id": obj.object_id,
        "geometry": {"type": "Point", "coordinates": [float(v) for v in obj.position]},
        "properties": props,
    }


def trajectory_feature(robot_id: str, stamps: ArrayLike, positions: ArrayLike) -> dict[str, Any]:
    """A robot's keyframe path as a LineString feature.

    Args:
        robot_id: the robot.
        stamps: (N,) capture times, seconds since the Unix epoch, ascending.
        positions: (N, 3) camera positions in the map frame, metres; N >= 1.

    Raises:
        ValueError: empty, or the shapes disagree.
    """
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] != t.shape[0] or t.shape[0] == 0:
        raise ValueError(f"trajectory of {robot_id!r}: expected N >= 1 stamps and (N, 3) positions, "
                         f"got {t.shape} and {p.shape}")
    coords = p.tolist()
    geometry = ({"type": "LineString", "coordinates": coords} if len(coords) > 1
                else {"type": "Point", "coordinates": coords[0]})
    return {
        "type": "Feature",
        "id": f"trajectory/{robot_id}",
        "geometry": geometry,
        "properties": {"robot_id": robot_id, "kind": "trajectory", "stamps": t.tolist()},
    }


def feature_collection(
    objects: Iterable[MapObject],
    trajectories: Sequence[dict[str, Any]] = (),
    **members: Any,
) -> dict[str, Any]:
    """A FeatureCollection of the objects' features, then the given trajectory features.

    Args:
        objects: map objects, in the order wanted.
        trajectories: features from :func:`trajectory_feature`.
        members: further foreign members of the collection (e.g. ``next_offset`` of a page).
    """
    out: dict[str, Any] = {
        "type": "FeatureCollection",
        "features": [object_feature(o) for o in objects] + list(trajectories),
        "wardmap": dict(FRAME_MEMBER),
    }
    out.update(_checked_members(members))
    return out


def _checked_members(members: Mapping[str, Any]) -> dict[str, Any]:
    reserved = {"type", "features", "wardmap", "bbox"} & set(members)
    if reserved:
        raise ValueError(f"foreign members may not be named {sorted(reserved)}")
    return dict(members)
