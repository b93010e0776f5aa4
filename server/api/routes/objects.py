"""``GET /v1/objects`` and ``GET /v1/objects/{object_id}``: the object map.

Objects are the shared map message (``shared/mapwire.py``, built by
``server/mapmessages.py``), the same shape the Zenoh queryable sends. The list also comes as
GeoJSON (``?format=geojson`` or ``Accept: application/geo+json``; ``shared/geojson.py``).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Header, HTTPException, Query
from fastapi.responses import JSONResponse

from wardmap.server.api.deps import ObjectMapDep
from wardmap.server.api.fastjson import FastJSONResponse
from wardmap.server.api.schemas import (
    ErrorOut,
    Flag,
    InvalidOut,
    KeyframeRefOut,
    ObjectDetailOut,
    ObjectList,
    ObjectOut,
    ObservationOut,
)
from wardmap.server.mapmessages import map_object
from wardmap.server.objectmap import (
    DEFAULT_LIMIT,
    MAX_LIMIT,
    MAX_OBSERVATIONS,
    MAX_OFFSET,
    CompactRow,
    ObjectMapError,
    ObjectQuery,
    parse_near,
)
from wardmap.shared import geojson
from wardmap.shared.mapwire import object_to_wire
from wardmap.shared.se3 import rotation_to_quat

router = APIRouter()

FORMATS = ("json", "geojson", "compact")
"""What ``GET /v1/objects?format=`` accepts; anything else is 400."""
COMPACT_COLUMNS = ("object_id", "category", "x", "y", "z", "yaw", "size_x", "size_y", "size_z")
"""The rows of ``format=compact``: what a floor view draws, metres and radians rounded to 1e-3."""


def _compact_row(row: CompactRow) -> list[Any]:
    oid, category, x, y, z, yaw, sx, sy, sz = row
    return [oid, category, round(x, 3), round(y, 3), round(z, 3), round(yaw, 3), round(sx, 3), round(sy, 3),
            round(sz, 3)]


def _vec(values: Any) -> list[float]:
    return [float(v) for v in values]


@router.get(
    "/v1/objects",
    response_model=None,
    responses={
        200: {"model": ObjectList},
        400: {"model": ErrorOut, "description": "an unknown `format`"},
        422: {"model": InvalidOut, "description": "a bad filter or parameter"},
    },
)
# async: the work is short and mostly GIL-bound Python, so a worker-thread hop only adds latency.
async def objects(
    objects: ObjectMapDep,
    category: Annotated[str | None, Query(max_length=64, description="knowledge-graph class")] = None,
    near: Annotated[
        str | None,
        Query(max_length=200, description="world point `x,y,z` in metres: nearest first, with distance"),
    ] = None,
    radius: Annotated[float | None, Query(description="metres (>= 0) around `near`; needs `near`")] = None,
    min_confidence: Annotated[float | None, Query(description="in [0, 1]")] = None,
    robot: Annotated[str | None, Query(max_length=64, description="seen by this robot")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_LIMIT)] = DEFAULT_LIMIT,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
    include_unconfirmed: Annotated[
        Flag, Query(description="also objects association has not confirmed (`confirmed` false)")
    ] = "false",
    format: Annotated[
        str | None,
        Query(max_length=32,
              description="`json` (default), `geojson` (a FeatureCollection, map-frame metres) or "
                          "`compact` (`columns` and `rows`: id, category, centre, yaw, size; for map views)"),
    ] = None,
    accept: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> JSONResponse:
    """Objects matching every filter; nearest centre first when `near` is given, else by id.
    As GeoJSON with `format=geojson` or `Accept: application/geo+json`."""
    if format is not None and format not in FORMATS:
        raise HTTPException(400, f"unknown format {format[:32]!r}: expected one of {', '.join(FORMATS)}")
    as_geojson = format == "geojson" or (format is None and geojson.MEDIA_TYPE in (accept or ""))
    try:
        centre = None if near is None else parse_near(near)
        query = ObjectQuery(category, centre, radius, min_confidence, robot, limit, offset,
                            include_unconfirmed == "true")
        if format == "compact":  # the web page's map: no records built, far fewer bytes than json
            compact = objects.find_compact(query)
            rows = [_compact_row(r) for r in compact.rows]
            return FastJSONResponse({"columns": COMPACT_COLUMNS, "rows": rows,
                                     "limit": limit, "offset": offset, "next_offset": compact.next_offset})
        page = objects.find(query)
    except ObjectMapError as exc:
        raise HTTPException(422, str(exc)) from exc
    if as_geojson:
        return JSONResponse(
            geojson.feature_collection((map_object(hit.record, hit.distance_m) for hit in page.hits),
                                       limit=limit, offset=offset, next_offset=page.next_offset),
            media_type=geojson.MEDIA_TYPE,
        )
    # The JSON is built without pydantic (latency); the tests validate it against ObjectList.
    return FastJSONResponse({
        "objects": [object_to_wire(map_object(hit.record, hit.distance_m)) for hit in page.hits],
        "limit": limit, "offset": offset, "next_offset": page.next_offset,
    })


@router.get(
    "/v1/objects/{object_id}",
    response_model=ObjectDetailOut,
    responses={404: {"model": ErrorOut}, 422: {"model": InvalidOut}},
)
def object_detail(
    objects: ObjectMapDep,
    object_id: int,
    observations: Annotated[int, Query(ge=0, le=MAX_OBSERVATIONS)] = 100,
) -> ObjectDetailOut:
    """One object with its latest observations and the keyframes they came from."""
    try:
        detail = objects.get(object_id, max_observations=observations)
    except ObjectMapError as exc:
        raise HTTPException(422, str(exc)) from exc
    if detail is None:
        raise HTTPException(404, f"unknown object {object_id}")
    return ObjectDetailOut(
        object=ObjectOut.model_validate(object_to_wire(map_object(detail.record))),
        observations=[
            ObservationOut(
                observation_id=o.observation_id, robot_id=o.robot_id, session_id=o.session_id,
                seq=o.seq, stamp=o.stamp, added_s=o.added_s, category=o.category,
                confidence=o.confidence, box_xyxy=_vec(o.box_xyxy),
                position=_vec(o.T_world_object[:3, 3]),
                q_xyzw=_vec(rotation_to_quat(o.T_world_object[:3, :3])), size=_vec(o.size),
            )
            for o in detail.observations
        ],
        keyframes=[
            KeyframeRefOut(robot_id=k.robot_id, session_id=k.session_id, seq=k.seq, stamp=k.stamp,
                           stored=k.stored)
            for k in detail.keyframes
        ],
    )
