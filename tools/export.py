"""``wardmap export``: the object map and the robots' paths as a file for other tools.

Sources:

- a server database, ``sqlite:///PATH`` (what ``wardmap server --db`` writes): every object
  (confirmed only unless asked) and each robot's trajectory on the map (its anchored sessions'
  optimised keyframe poses; a robot with no anchored session has none and is counted);
- a ``wardmap map`` output (its folder or ``landmarks.json``): every landmark as an object.
  That file has no trajectories and no server times, so those properties are absent.

Formats: ``geojson`` (``shared/geojson.py``: map-frame metres, not WGS84). The file is
written to a temporary name beside ``out`` and renamed, so a failed export leaves no partial
file.
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Any, Final

import numpy as np

from wardmap.server.mapmessages import map_object
from wardmap.server.objectmap import MAX_LIMIT, ObjectMap, ObjectQuery
from wardmap.server.store import SQLITE_SCHEME, open_store
from wardmap.shared import geojson
from wardmap.shared.errors import WardmapError

log = logging.getLogger(__name__)

__all__ = ["FORMATS", "ExportError", "export", "landmarks_geojson", "store_geojson"]

FORMATS: Final = ("geojson",)


class ExportError(WardmapError):
    """The source cannot be read or the output cannot be written."""


def store_geojson(db_url: str, *, include_unconfirmed: bool = False) -> dict[str, Any]:
    """The FeatureCollection of a server database: objects by id, then one trajectory per robot
    that has a map trajectory.

    Raises:
        ExportError: the database file does not exist.
        StoreError: it cannot be opened.
    """
    path = db_url[len(SQLITE_SCHEME):].partition("?")[0] if db_url.startswith(SQLITE_SCHEME) else None
    if path is not None and not Path(path).is_file():
        raise ExportError(f"no database at {path}")
    with open_store(db_url) as store:
        objects = ObjectMap(store)
        found = []
        offset: int | None = 0
        while offset is not None:
            query = ObjectQuery(limit=MAX_LIMIT, offset=offset, include_unconfirmed=include_unconfirmed)
            page = objects.find(query)
            found += [map_object(hit.record) for hit in page.hits]
            offset = page.next_offset
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


def export(
    source: str, out: str | Path, *, fmt: str = "geojson", include_unconfirmed: bool = False
) -> dict[str, int]:
    """Export ``source`` (``sqlite:///PATH``, or a ``wardmap map`` folder / landmarks.json) to
    ``out`` in ``fmt``.

    Returns:
        ``{"objects": n, "trajectories": m}`` written.

    Raises:
        ExportError: unknown format, unreadable source, or ``out`` cannot be written.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}: expected one of {', '.join(FORMATS)}")
    if source.startswith(SQLITE_SCHEME):
        doc = store_geojson(source, include_unconfirmed=include_unconfirmed)
    else:
        doc = landmarks_geojson(source)
    kinds = [f["properties"].get("kind") for f in doc["features"]]
    out_path = Path(out)
    tmp = out_path.with_name(out_path.name + ".part")
    try:
        tmp.write_text(json.dumps(doc) + "\n", encoding="utf-8")
        os.replace(tmp, out_path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ExportError(f"cannot write {out_path}: {exc.strerror or exc}") from exc
    return {"objects": kinds.count(None), "trajectories": kinds.count("trajectory")}
