"""``GET /v1/keyframes?robot=ID``: a robot's stored keyframes, paged by an opaque cursor;
``GET /v1/keyframes/{robot_id}/{session_id}/{seq}/image``: a stored keyframe's colour image."""

from __future__ import annotations

import base64
import binascii
import json
from typing import Annotated

from fastapi import APIRouter, HTTPException, Path, Query
from fastapi.responses import Response

from wardmap.server.api.deps import StoreDep
from wardmap.server.api.schemas import ErrorOut, KeyframeList, KeyframeOut
from wardmap.server.store import MAX_PAGE
from wardmap.shared import wire
from wardmap.shared.errors import WireError

__all__ = ["decode_cursor", "encode_cursor", "router"]

router = APIRouter()


def encode_cursor(session_id: str, seq: int) -> str:
    """Opaque page cursor for ``(session_id, seq)``: urlsafe base64 of a JSON pair."""
    return base64.urlsafe_b64encode(json.dumps([session_id, seq]).encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[str, int]:
    """Inverse of :func:`encode_cursor`; raises ValueError on anything else."""
    try:
        raw = base64.b64decode(cursor + "=" * (-len(cursor) % 4), altchars=b"-_", validate=True)
        value = json.loads(raw)
    except (binascii.Error, ValueError, UnicodeDecodeError) as exc:
        raise ValueError("malformed cursor") from exc
    if (
        not isinstance(value, list) or len(value) != 2 or not isinstance(value[0], str)
        or isinstance(value[1], bool) or not isinstance(value[1], int)
    ):
        raise ValueError("malformed cursor")
    return value[0], value[1]


@router.get("/v1/keyframes", response_model=KeyframeList, responses={400: {"model": ErrorOut}})
def keyframes(
    store: StoreDep,
    robot: Annotated[str, Query(min_length=1, max_length=64)],
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 100,
    cursor: Annotated[str | None, Query(max_length=512)] = None,
) -> KeyframeList:
    after = None
    if cursor is not None:
        try:
            after = decode_cursor(cursor)
        except ValueError as exc:
            raise HTTPException(400, f"bad cursor {cursor[:80]!r}") from exc
    page = store.keyframes(robot, after=after, limit=limit)
    return KeyframeList(
        keyframes=[
            KeyframeOut(robot_id=r.robot_id, session_id=r.session_id, seq=r.seq, stamp=r.stamp,
                        received_s=r.received_s, pose_source=r.pose_source, payload_bytes=r.payload_bytes)
            for r in page.rows
        ],
        next_cursor=None if page.next_cursor is None else encode_cursor(*page.next_cursor),
    )


@router.get(
    "/v1/keyframes/{robot_id}/{session_id}/{seq}/image",
    response_class=Response,
    responses={200: {"content": {"image/jpeg": {}}, "description": "the colour JPEG the robot sent"},
               404: {"model": ErrorOut},
               410: {"model": ErrorOut, "description": "the image was erased (retention or an erase order)"}},
)
def keyframe_image(
    store: StoreDep,
    robot_id: Annotated[str, Path(min_length=1, max_length=64)],
    session_id: Annotated[str, Path(min_length=1, max_length=64)],
    seq: Annotated[int, Path(ge=0)],
) -> Response:
    """The keyframe's colour image as the robot sent it (JPEG; the web page's thumbnail);
    410 once it was erased (``[store] image_retention``, ``wardmap images erase``)."""
    payload = store.payload(robot_id, session_id, seq)
    if payload is None:
        raise HTTPException(404, f"no keyframe {robot_id}/{session_id}/{seq}")
    erased_s = store.images_erased_s(robot_id, session_id, seq)
    if erased_s is not None:
        raise HTTPException(410, f"the image of keyframe {robot_id}/{session_id}/{seq} was erased at "
                                 f"{erased_s:.0f} (server seconds): retention or an erase order")
    try:
        msg = wire.decode_keyframe(payload)
    except WireError as exc:  # stored after validation: only a damaged row gets here
        raise HTTPException(500, f"keyframe {robot_id}/{session_id}/{seq} cannot be read: {exc}") from exc
    return Response(msg.rgb_jpeg, media_type="image/jpeg", headers={"Cache-Control": "max-age=3600"})
