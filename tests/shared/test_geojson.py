"""``shared/geojson.py``: map objects and trajectories as GeoJSON features, checked with the
``geojson`` library."""

from __future__ import annotations

import json

import geojson as gj
import numpy as np
import pytest

from wardmap.shared.geojson import feature_collection, object_feature, trajectory_feature
from wardmap.shared.mapwire import MapObject


def _object(oid: int = 7) -> MapObject:
    return MapObject(
        object_id=oid, category="door", confidence=0.9, position=(1.0, 2.0, 1.05),
        q_xyzw=(0.0, 0.0, 0.0, 1.0), yaw=0.0, size=(0.9, 0.1, 2.1), bounds_min=(0.55, 1.95, 0.0),
        bounds_max=(1.45, 2.05, 2.1), color_rgb=(200.0, 10.0, 5.0), n_observations=3,
        first_seen_s=100.0, last_seen_s=200.0, robots=("r1",), confirmed=True, distance_m=None,
    )


def test_collection_of_objects_and_trajectories_is_valid_geojson() -> None:
    """Objects become Points at their centres, a trajectory a LineString of its positions with
    its stamps; the whole is valid GeoJSON and JSON-serialisable."""
    stamps = np.array([1.0, 2.0, 3.0])
    positions = np.array([[0.0, 0.0, 1.2], [1.0, 0.0, 1.2], [2.0, 0.5, 1.2]])
    path = trajectory_feature("r1", stamps, positions)
    doc = feature_collection([_object(7), _object(8)], [path], next_offset=None)
    parsed = gj.loads(json.dumps(doc))
    assert parsed.is_valid, parsed.errors()
    kinds = [f["geometry"]["type"] for f in doc["features"]]
    assert kinds == ["Point", "Point", "LineString"]
    assert doc["features"][0]["geometry"]["coordinates"] == [1.0, 2.0, 1.05]
    assert doc["features"][0]["properties"]["color_rgb"] == (200.0, 10.0, 5.0)
    assert "position" not in doc["features"][0]["properties"]
    line = doc["features"][2]
    assert line["geometry"]["coordinates"] == positions.tolist()
    assert line["properties"]["stamps"] == [1.0, 2.0, 3.0]
    assert doc["next_offset"] is None and doc["wardmap"] == {"frame": "map", "units": "m"}


def test_one_keyframe_is_a_point_and_bad_shapes_raise() -> None:
    """A path of one position is a Point (a LineString needs two); mismatched or empty input
    raises ValueError naming the robot."""
    f = trajectory_feature("r2", [5.0], [[1.0, 2.0, 3.0]])
    assert f["geometry"] == {"type": "Point", "coordinates": [1.0, 2.0, 3.0]}
    with pytest.raises(ValueError, match="'r2'"):
        trajectory_feature("r2", [1.0, 2.0], [[1.0, 2.0, 3.0]])
    with pytest.raises(ValueError, match="'r2'"):
        trajectory_feature("r2", [], np.zeros((0, 3)))
    with pytest.raises(ValueError, match="features"):
        feature_collection([], features=[])
    assert object_feature(_object())["id"] == 7
