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


@pytest.mark.parametrize("backend", ["sqlite", "postgres"])
def test_server_database_to_geojson(tmp_path: Path, backend: str, request: pytest.FixtureRequest) -> None:
    """The ward's 5 objects become Points at their centres (by id); r1, anchored, gets its
    6-keyframe path as a LineString at the camera positions; r2, not anchored, has none and
    is named; an unconfirmed object comes only when asked. The same from a PostgreSQL database."""
    url = f"sqlite:///{tmp_path / 'map.db'}"
    if backend == "postgres":
        cluster = request.getfixturevalue("pg_cluster")
        url = cluster.url(cluster.new_database())
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
    with pytest.raises(ExportError, match="unknown format 'obj'"):
        export(str(tmp_path), tmp_path / "o.obj", fmt="obj")
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


def test_server_database_to_ply(tmp_path: Path) -> None:
    """One anchored keyframe sees a flat wall 2 m ahead (the camera looks along the map's +x);
    one floating keyframe is not fused. The PLY (read back with trimesh) holds the red box's 8
    corners and 12 triangles in its colour, then 48 wall points (every 4th of the 32 x 24 depth
    pixels, 0.32 m apart, so the 5 cm voxels keep each) on the plane x = 2 m, in the image's
    colours."""
    import dataclasses

    import factories
    import trimesh

    from wardmap.server.store import GraphChange, GraphNodeRow, SessionAnchor
    from wardmap.shared import wire

    url = f"sqlite:///{tmp_path / 'map.db'}"
    T = webscene.camera_at(0.0, 0.0)
    wall = wire.PackedRaster(*wire.encode_depth(np.full((factories.H // 2, factories.W // 2), 2.0)))
    base = dataclasses.replace(factories.keyframe(np.random.default_rng(3)), depth=wall, T_odom_camera=T)
    with open_store(url) as store:
        for robot in ("r1", "r2"):
            msg = dataclasses.replace(base, robot_id=robot)
            assert store.insert(msg, wire.encode(msg), 10.0) == "stored"
        store.commit_graph("backend", 2, GraphChange(
            [GraphNodeRow(("r1", "s1", 0), base.stamp, T, "rgb", T, None, b""),
             GraphNodeRow(("r2", "s1", 0), base.stamp, T, "rgb", None, None, b"")],
            sessions=[SessionAnchor("r1", "s1", np.eye(4), 11.0, "r1/s1", 1)]))
        ObjectMap(store).upsert([ObjectState(1, "cabinet", 0.9, yaw_transform(3.0, 1.0, 0.3, 0.5),
                                             np.array([1.0, 0.5, 1.0]), color_rgb=(200.0, 20.0, 10.0))])
    out = tmp_path / "map.ply"
    calls: list[tuple[str, int, int]] = []
    summary = export(url, out, fmt="ply", progress=lambda *call: calls.append(call))
    assert summary == {"objects": 1, "points": 48, "keyframes": 1, "keyframes_skipped": 0}
    assert calls == [("ply", 1, 2), ("ply", 2, 2)]  # per graph node, the floating one too
    mesh = trimesh.load(out, process=False)
    assert len(mesh.vertices) == 8 + 48 and len(mesh.faces) == 12
    assert np.allclose(mesh.vertices[:8].mean(axis=0), [3.0, 1.0, 0.5])
    assert (mesh.visual.vertex_colors[:8, :3] == [200, 20, 10]).all()
    assert np.allclose(mesh.vertices[8:, 0], 2.0)
    rgb = mesh.visual.vertex_colors[8:, :3].astype(int)
    assert len({tuple(c) for c in rgb}) > 10  # the noise image's colours, not one flat colour
    with pytest.raises(ExportError, match="needs a server database"):
        export(str(tmp_path), tmp_path / "x.ply", fmt="ply")


@pytest.mark.parametrize(("fmt", "module", "extra"),
                         [("ply", "trimesh", "export"), ("rrd", "rerun", "rerun")])
def test_without_the_extra_says_what_to_install(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fmt: str, module: str, extra: str
) -> None:
    """Without its extra's package the PLY or RRD export is one clear error, before it reads
    anything or writes a file."""
    import sys

    monkeypatch.setitem(sys.modules, module, None)  # importing it now raises ImportError
    with pytest.raises(ExportError, match=rf"pip install 'wardmap\[{extra}\]'"):
        export(f"sqlite:///{tmp_path / 'map.db'}", tmp_path / f"m.{fmt}", fmt=fmt)
    assert not list(tmp_path.iterdir())


def test_server_database_to_rerun_recording(tmp_path: Path) -> None:
    """The ward as a Rerun recording, read back with rerun's own reader: r1's 6 anchored
    keyframes as camera poses and JPEG images on the ``time`` timeline, its path (static), each
    of the 5 objects as a box; r2, not anchored, logs nothing."""
    from rerun.chunk import RrdReader

    url = f"sqlite:///{tmp_path / 'map.db'}"
    webscene.fill_ward(url)
    out = tmp_path / "map.rrd"
    assert export(url, out, fmt="rrd") == {"objects": 5, "keyframes": 6, "trajectories": 1}
    rows: dict[str, int] = {}
    columns: dict[str, set[str]] = {}
    for chunk in RrdReader(out).stream().to_chunks():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
        columns.setdefault(chunk.entity_path, set()).update(chunk.to_record_batch().schema.names)
    camera = "/map/robots/r1/camera"
    assert rows[camera] == 6 and "Transform3D:translation" in columns[camera]
    assert {"EncodedImage:blob", "Pinhole:image_from_camera", "time"} <= columns[f"{camera}/image"]
    assert rows["/map/robots/r1/path"] == 1
    objects = sorted(p for p in rows if p.startswith("/map/objects/"))
    assert objects == [f"/map/objects/{i}" for i in range(1, 6)]
    assert "Boxes3D:half_sizes" in columns["/map/objects/4"]
    assert not [p for p in rows if p.startswith("/map/robots/r2")]
    assert not list(tmp_path.glob("*.part"))
