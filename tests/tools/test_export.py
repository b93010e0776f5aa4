"""``wardmap export`` (``tools/export.py``, ``cli/export_cmd.py``): a server database or a
``wardmap map`` output as GeoJSON, validated with the ``geojson`` library."""

from __future__ import annotations

import json
from pathlib import Path

import geojson as gj
import numpy as np
import pytest
import webscene
from procs import one_line_error, wardmap

from wardmap.server.objectmap import ObjectMap, ObjectState
from wardmap.server.store import open_store
from wardmap.shared.se3 import yaw_transform
from wardmap.tools.export import ExportError, export


def _load(path: Path) -> dict:
    text = path.read_text()
    parsed = gj.loads(text)
    assert parsed.is_valid, parsed.errors()
    return json.loads(text)


def test_server_database_to_geojson(tmp_path: Path) -> None:
    """The ward's 5 objects become Points at their centres (by id); r1, anchored, gets its
    6-keyframe path as a LineString at the camera positions; r2, not anchored, has none and
    is named; an unconfirmed object comes only when asked."""
    url = f"sqlite:///{tmp_path / 'map.db'}"
    webscene.fill_ward(url)
    with open_store(url) as store:
        ObjectMap(store).upsert([ObjectState(9, "cabinet", 0.5, yaw_transform(1, 1, 0, 1), np.ones(3),
                                             confirmed=False)])
    out = tmp_path / "map.geojson"
    assert export(url, out) == {"objects": 5, "trajectories": 1}
    doc = _load(out)
    points = [f for f in doc["features"] if f["geometry"]["type"] == "Point"]
    assert [f["id"] for f in points] == [1, 2, 3, 4, 5]
    centres = [[x, y, z] for _, _, x, y, z, _ in webscene.OBJECTS]
    assert [f["geometry"]["coordinates"] for f in points] == centres
    assert points[1]["properties"]["robots"] == ["r1"] and points[1]["properties"]["category"] == "door"
    (line,) = [f for f in doc["features"] if f["geometry"]["type"] == "LineString"]
    assert line["properties"]["robot_id"] == "r1" and line["properties"]["kind"] == "trajectory"
    assert np.allclose(line["geometry"]["coordinates"], [[2.0 * k, 0.0, 1.2] for k in range(6)])
    assert doc["robots_without_map_trajectory"] == ["r2"]
    assert export(url, out, include_unconfirmed=True)["objects"] == 6
    assert not list(tmp_path.glob("*.part"))


def test_map_output_to_geojson(tmp_path: Path) -> None:
    """A ``wardmap map`` folder's landmarks become Points with class, yaw, size and their
    measurement count."""
    T = yaw_transform(2.0, 3.0, 0.5, 0.4)
    (tmp_path / "landmarks.json").write_text(json.dumps({"format_version": 1, "landmarks": [
        {"id": 4, "class": "chair", "confirmed": True, "confidence": 0.7, "T_world_object": T.tolist(),
         "size": [0.5, 0.5, 0.8], "color_rgb": [10, 20, 30], "measurements": [{}, {}]}]}))
    out = tmp_path / "out.geojson"
    assert export(str(tmp_path), out) == {"objects": 1, "trajectories": 0}
    (f,) = _load(out)["features"]
    assert np.allclose(f["geometry"]["coordinates"], [2.0, 3.0, 0.4])
    assert f["properties"]["yaw"] == pytest.approx(0.5)
    assert f["properties"]["category"] == "chair" and f["properties"]["n_observations"] == 2


def test_bad_sources(tmp_path: Path) -> None:
    """A missing database is an error (not a new empty one); a file that is not a map output
    names what is wrong; an unknown format is refused."""
    with pytest.raises(ExportError, match="no database at"):
        export(f"sqlite:///{tmp_path / 'nope.db'}", tmp_path / "o.geojson")
    assert not (tmp_path / "nope.db").exists()
    (tmp_path / "landmarks.json").write_text('{"landmarks": [{"id": 1}]}')
    with pytest.raises(ExportError, match=r"landmarks\[0\]"):
        export(str(tmp_path), tmp_path / "o.geojson")
    with pytest.raises(ExportError, match="unknown format 'ply'"):
        export(str(tmp_path), tmp_path / "o.ply", fmt="ply")
    assert not (tmp_path / "o.geojson").exists()


def test_cli_exports_and_fails_in_one_line(tmp_path: Path) -> None:
    """``wardmap export sqlite:///... --out FILE`` prints a JSON summary; a missing source is
    one line on stderr and exit 1."""
    url = f"sqlite:///{tmp_path / 'map.db'}"
    webscene.fill_ward(url)
    p = wardmap("export", url, "--out", str(tmp_path / "m.geojson"))
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout.splitlines()[-1]) == {"out": str(tmp_path / "m.geojson"), "objects": 5,
                                                     "trajectories": 1}
    one_line_error(wardmap("export", str(tmp_path / "none"), "--out", str(tmp_path / "x.geojson")),
                   "cannot read", "export")
