"""``wardmap export``: the object map, the robots' paths and a point cloud as files for other tools.

Sources:

- a server database, ``sqlite:///PATH`` (what ``wardmap server --db`` writes): every object
  (confirmed only unless asked) and each robot's trajectory on the map (its anchored sessions'
  optimised keyframe poses; a robot with no anchored session has none and is counted);
- a ``wardmap map`` output (its folder or ``landmarks.json``): every landmark as an object.
  That file has no trajectories and no server times, so those properties are absent.

Formats:

- ``geojson`` (``shared/geojson.py``: map-frame metres, not WGS84);
- ``ply`` (a server database only; the ``export`` extra, trimesh): one binary PLY in the map
  frame whose faces are the objects' boxes (8 vertices, 12 triangles each, in the object's
  colour, grey when unknown) and whose remaining vertices, after the boxes', are a coloured
  point cloud: the depth of every keyframe with a map pose, every :data:`PLY_STRIDE`-th depth
  pixel, back-projected with its colour and thinned to one point per :data:`PLY_VOXEL_M` voxel.
- ``rrd`` (a server database only; the ``rerun`` extra, rerun-sdk): a Rerun recording, map
  frame z up. Timeline ``time`` (Unix seconds): each anchored keyframe's camera
  (``map/robots/<id>/camera``: its pose, pinhole and colour JPEG) at its capture stamp, each
  object's box (``map/objects/<id>``) from the server time it was first seen; static: each
  robot's map trajectory (``map/robots/<id>/path``).

The file is written to a temporary name beside ``out`` and renamed, so a failed export leaves
no partial file.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np

from wardmap.server.mapmessages import map_object
from wardmap.server.objectmap import MAX_LIMIT, ObjectMap, ObjectQuery
from wardmap.server.store import SQLITE_SCHEME, open_store
from wardmap.shared import geojson, wire
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import WardmapError
from wardmap.shared.se3 import make_transform, quat_to_rotation

log = logging.getLogger(__name__)

__all__ = [
    "FORMATS", "ExportError", "export", "keyframe_points", "landmarks_geojson", "store_geojson", "store_ply",
    "store_rrd",
]

FORMATS: Final = ("geojson", "ply", "rrd")
Progress = Callable[[str, int, int], None]
"""``progress(task, done, total)``: called as keyframes are written (PLY, RRD)."""
PLY_STRIDE: Final = 4
"""Every this-th depth pixel along each axis goes into the point cloud."""
PLY_VOXEL_M: Final = 0.05
"""The point cloud keeps the first point of each voxel of this side (metres)."""
PLY_MAX_DEPTH_M: Final = 6.0
"""Depth beyond this (metres) is left out: far readings are the noisiest."""
_GREY: Final = (160, 160, 160)


class ExportError(WardmapError):
    """The source cannot be read or the output cannot be written."""


def store_geojson(db_url: str, *, include_unconfirmed: bool = False) -> dict[str, Any]:
    """The FeatureCollection of a server database: objects by id, then one trajectory per robot
    that has a map trajectory.

    Raises:
        ExportError: the database file does not exist.
        StoreError: it cannot be opened.
    """
    _check_db(db_url)
    with open_store(db_url) as store:
        found = [map_object(r) for r in _map_objects(store, include_unconfirmed)]
        trajectories = []
        floating = []
        for robot in store.robots():
            stamps, T_map_camera = store.map_trajectory(robot.robot_id)
            if len(stamps) == 0:
                floating.append(robot.robot_id)
                continue
            trajectories.append(geojson.trajectory_feature(robot.robot_id, stamps, T_map_camera[:, :3, 3]))
    if floating:
        log.info("no map trajectory (no anchored session) for robots %s", ", ".join(floating))
    return geojson.feature_collection(found, trajectories, robots_without_map_trajectory=floating)


def landmarks_geojson(path: str | Path) -> dict[str, Any]:
    """The FeatureCollection of a ``wardmap map`` output (``landmarks.json`` or its folder).

    Each landmark is a Point at its box centre with ``object_id``, ``category``,
    ``confirmed``, ``confidence``, ``yaw`` (rad, about z), ``size`` (m), ``color_rgb`` and
    ``n_observations`` (its measurements).

    Raises:
        ExportError: the file is missing, not JSON, or not a landmarks document.
    """
    file = Path(path)
    if file.is_dir():
        file = file / "landmarks.json"
    try:
        doc = json.loads(file.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ExportError(f"cannot read {file}: {exc.strerror or exc}") from exc
    except ValueError as exc:
        raise ExportError(f"{file} is not JSON: {exc}") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("landmarks"), list):
        raise ExportError(f"{file} is not a `wardmap map` output: no landmarks list")
    features = []
    for i, lm in enumerate(doc["landmarks"]):
        try:
            T = np.asarray(lm["T_world_object"], dtype=np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError("T_world_object is not a finite 4x4 matrix")
            props = {
                "object_id": int(lm["id"]), "category": str(lm["class"]),
                "confirmed": bool(lm["confirmed"]), "confidence": float(lm["confidence"]),
                "yaw": math.atan2(T[1, 0], T[0, 0]), "size": [float(v) for v in lm["size"]],
                "color_rgb": lm.get("color_rgb"), "n_observations": len(lm.get("measurements", [])),
            }
        except (KeyError, TypeError, ValueError) as exc:
            raise ExportError(f"{file}: landmarks[{i}]: {exc}") from exc
        features.append({"type": "Feature", "id": props["object_id"],
                         "geometry": {"type": "Point", "coordinates": T[:3, 3].tolist()},
                         "properties": props})
    return {"type": "FeatureCollection", "features": features, "wardmap": dict(geojson.FRAME_MEMBER)}


def _map_objects(store: Any, include_unconfirmed: bool) -> list[Any]:
    objects = ObjectMap(store)
    found = []
    offset: int | None = 0
    while offset is not None:
        query = ObjectQuery(limit=MAX_LIMIT, offset=offset, include_unconfirmed=include_unconfirmed)
        page = objects.find(query)
        found += [hit.record for hit in page.hits]
        offset = page.next_offset
    return found


def keyframe_points(msg: wire.KeyframeMsg, T_map_camera: np.ndarray, stride: int = PLY_STRIDE
                    ) -> tuple[np.ndarray, np.ndarray]:
    """A keyframe's depth as map points with their colours.

    Args:
        msg: the keyframe; its ``intrinsics`` must be set.
        T_map_camera: (4, 4) its colour camera's pose on the map.
        stride: every ``stride``-th depth pixel along each axis.

    Returns:
        points (N, 3) float64 map-frame metres, colours (N, 3) uint8 RGB; pixels without depth
        (0) or beyond :data:`PLY_MAX_DEPTH_M` are left out.
    """
    if msg.intrinsics is None:
        raise ValueError("keyframe has no intrinsics")
    i = msg.intrinsics
    camera = PinholeCamera(i.width, i.height, i.fx, i.fy, i.cx, i.cy, tuple(i.distortion))  # type: ignore[arg-type]
    depth_m = wire.decode_depth(msg.depth.data, msg.depth.meta)
    bgr = cv2.imdecode(np.frombuffer(msg.rgb_jpeg, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("colour JPEG cannot be decoded")
    scale = bgr.shape[1] // depth_m.shape[1]  # depth pixel (r, c) covers colour pixel (s r, s c)
    rows, cols = np.mgrid[0:depth_m.shape[0]:stride, 0:depth_m.shape[1]:stride]
    d = depth_m[rows, cols].reshape(-1)
    keep = (d > 0) & (d <= PLY_MAX_DEPTH_M)
    u, v = (cols.reshape(-1)[keep] * scale), (rows.reshape(-1)[keep] * scale)
    points_cam = camera.unproject(np.column_stack([u, v]).astype(np.float64), d[keep])
    points_map = points_cam @ T_map_camera[:3, :3].T + T_map_camera[:3, 3]
    return points_map, bgr[v, u, ::-1].astype(np.uint8)


def _voxel_thin(points: np.ndarray, colours: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    if len(points) == 0:
        return points, colours
    _, first = np.unique(np.floor(points / voxel_m).astype(np.int64), axis=0, return_index=True)
    first.sort()
    return points[first], colours[first]


def store_ply(db_url: str, out: Path, *, include_unconfirmed: bool = False,
              progress: Progress | None = None) -> dict[str, int]:
    """Write the PLY of the module docstring from a server database; returns the counts
    ``objects``, ``points``, ``keyframes`` (fused) and ``keyframes_skipped`` (no intrinsics
    or unreadable). ``progress("ply", done, total)`` after each keyframe."""
    try:
        import trimesh
    except ImportError as exc:
        raise ExportError("--format ply needs trimesh: pip install 'wardmap[export]'") from exc
    _check_db(db_url)
    vertices, faces, colours = [], [], []
    n_vertices = 0
    with open_store(db_url) as store:
        records = _map_objects(store, include_unconfirmed)
        for r in records:
            T = make_transform(quat_to_rotation(r.q_xyzw), r.position)
            box = trimesh.creation.box(extents=r.size, transform=T)
            rgb = _GREY if r.color_rgb is None else tuple(round(c) for c in r.color_rgb)
            vertices.append(np.asarray(box.vertices))
            faces.append(np.asarray(box.faces) + n_vertices)
            colours.append(np.tile(rgb, (len(box.vertices), 1)))
            n_vertices += len(box.vertices)
        nodes, _ = store.graph_records()
        cloud, cloud_rgb, fused, skipped = [], [], 0, 0
        for k, node in enumerate(nodes, 1):
            if progress is not None:
                progress("ply", k, len(nodes))
            if node.T_map_camera is None:
                continue
            payload = store.payload(*node.key)
            try:
                if payload is None:
                    raise ValueError("not stored")
                p, c = keyframe_points(wire.decode_keyframe(payload), node.T_map_camera)
            except (ValueError, WardmapError) as exc:
                log.warning("keyframe %s left out of the point cloud: %s", "/".join(map(str, node.key)), exc)
                skipped += 1
                continue
            cloud.append(p)
            cloud_rgb.append(c)
            fused += 1
    points, point_rgb = _voxel_thin(np.concatenate(cloud) if cloud else np.zeros((0, 3)),
                                    np.concatenate(cloud_rgb) if cloud_rgb else np.zeros((0, 3), np.uint8),
                                    PLY_VOXEL_M)
    mesh = trimesh.Trimesh(
        vertices=np.concatenate([*vertices, points]) if vertices or len(points) else np.zeros((0, 3)),
        faces=np.concatenate(faces) if faces else np.zeros((0, 3), np.int64),
        vertex_colors=np.concatenate([*colours, point_rgb]).astype(np.uint8) if colours or len(points)
        else None,
        process=False,  # keep the point cloud's vertices, which no face uses
    )
    data = mesh.export(file_type="ply")  # binary PLY: bytes
    if not isinstance(data, bytes):
        raise ExportError(f"trimesh wrote {type(data).__name__}, not PLY bytes")
    _write(out, data)
    return {"objects": len(records), "points": len(points), "keyframes": fused, "keyframes_skipped": skipped}


def store_rrd(db_url: str, out: Path, *, include_unconfirmed: bool = False,
              progress: Progress | None = None) -> dict[str, int]:
    """Write the Rerun recording of the module docstring from a server database; returns the
    counts ``objects``, ``keyframes`` (logged) and ``trajectories``. ``progress("rrd", done,
    total)`` after each keyframe."""
    try:
        import rerun as rr
    except ImportError as exc:
        raise ExportError("--format rrd needs rerun-sdk: pip install 'wardmap[rerun]'") from exc
    _check_db(db_url)
    tmp = out.with_name(out.name + ".part")
    rec = rr.RecordingStream("wardmap")
    try:
        rec.save(str(tmp))
        rec.log("map", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        with open_store(db_url) as store:
            records = _map_objects(store, include_unconfirmed)
            nodes, _ = store.graph_records()
            anchored = sorted([(n, T) for n in nodes if (T := n.T_map_camera) is not None],
                              key=lambda pair: pair[0].stamp)
            for k, (node, T) in enumerate(anchored, 1):
                if progress is not None:
                    progress("rrd", k, len(anchored))
                camera = f"map/robots/{node.key[0]}/camera"
                rec.set_time("time", timestamp=node.stamp)
                rec.log(camera, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
                payload = store.payload(*node.key)
                if payload is None:
                    continue
                msg = wire.decode_keyframe(payload)
                i = msg.intrinsics
                if i is not None:  # rerun's default camera axes are ours: x right, y down, z forward
                    pinhole = rr.Pinhole(focal_length=[i.fx, i.fy], principal_point=[i.cx, i.cy],
                                         width=i.width, height=i.height)
                    rec.log(f"{camera}/image", pinhole)
                rec.log(f"{camera}/image", rr.EncodedImage(contents=msg.rgb_jpeg, media_type="image/jpeg"))
            robots = [r.robot_id for r in store.robots()]
            paths = 0
            for robot in robots:
                _, T_map_camera = store.map_trajectory(robot)
                if len(T_map_camera) > 1:
                    path = rr.LineStrips3D([T_map_camera[:, :3, 3]])
                    rec.log(f"map/robots/{robot}/path", path, static=True)
                    paths += 1
        for r in records:
            rec.set_time("time", timestamp=r.first_seen_s)
            rgb = _GREY if r.color_rgb is None else tuple(round(c) for c in r.color_rgb)
            box = rr.Boxes3D(centers=[r.position], half_sizes=[[s / 2 for s in r.size]],
                             quaternions=[rr.Quaternion(xyzw=r.q_xyzw)],
                             labels=[f"{r.category} {r.object_id}"], colors=[rgb])
            rec.log(f"map/objects/{r.object_id}", box)
        rec.flush()
        rec.disconnect()
        os.replace(tmp, out)
    except OSError as exc:
        raise ExportError(f"cannot write {out}: {exc.strerror or exc}") from exc
    finally:
        tmp.unlink(missing_ok=True)
    return {"objects": len(records), "keyframes": len(anchored), "trajectories": paths}


def _is_store(source: str) -> bool:
    """Whether ``source`` is a server database URL (SQLite or PostgreSQL; the PostgreSQL password
    comes from WARDMAP_DB_PASSWORD or ~/.pgpass)."""
    return source.startswith((SQLITE_SCHEME, "postgresql://", "postgres://"))


def _check_db(db_url: str) -> None:
    path = db_url[len(SQLITE_SCHEME):].partition("?")[0] if db_url.startswith(SQLITE_SCHEME) else None
    if path is not None and not Path(path).is_file():
        raise ExportError(f"no database at {path}")


def _write(out: Path, data: bytes) -> None:
    tmp = out.with_name(out.name + ".part")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, out)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ExportError(f"cannot write {out}: {exc.strerror or exc}") from exc


def export(
    source: str, out: str | Path, *, fmt: str = "geojson", include_unconfirmed: bool = False,
    progress: Progress | None = None,
) -> dict[str, int]:
    """Export ``source`` (``sqlite:///PATH``, ``postgresql://USER@HOST:PORT/DB``, or a ``wardmap map``
    folder / landmarks.json) to ``out`` in ``fmt``.

    Returns:
        the counts written: ``{"objects", "trajectories"}`` (geojson), ``{"objects", "points",
        "keyframes", "keyframes_skipped"}`` (ply) or ``{"objects", "keyframes", "trajectories"}``
        (rrd).

    Raises:
        ExportError: unknown format, unreadable source, a missing extra, or ``out`` cannot be
            written.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}: expected one of {', '.join(FORMATS)}")
    if fmt in ("ply", "rrd"):
        if not _is_store(source):
            raise ExportError(f"--format {fmt} needs a server database (sqlite:///PATH or "
                              "postgresql://...): "
                              "a map output has no keyframes")
        writer = store_ply if fmt == "ply" else store_rrd
        return writer(source, Path(out), include_unconfirmed=include_unconfirmed, progress=progress)
    if _is_store(source):
        doc = store_geojson(source, include_unconfirmed=include_unconfirmed)
    else:
        doc = landmarks_geojson(source)
    kinds = [f["properties"].get("kind") for f in doc["features"]]
    _write(Path(out), (json.dumps(doc) + "\n").encode())
    return {"objects": kinds.count(None), "trajectories": kinds.count("trajectory")}
