"""``GET /v1/events``: the object map's changes as Server-Sent Events (the web page's live view).

Each stream subscribes in-process to the object map (:meth:`ObjectMap.add_listener`), the same
change events :class:`~wardmap.server.mapserve.MapServe` publishes on
``wardmap/v1/map/updates``, so the page needs no Zenoh and the server opens no second session.
Events (``text/event-stream``, UTF-8):

- ``ready`` (data ``{}``): sent once the stream is subscribed. A client that wants no gap
  loads its snapshot (``GET /v1/objects``) after ``ready`` and then applies the updates it
  received since, in order: every change committed after ``ready`` arrives, in commit order,
  and each carries the whole object, so the last one of an object is its state.
- ``update``: one :class:`~wardmap.shared.mapwire.MapUpdate` as JSON: ``{"kind": "created" |
  "updated" | "deleted", "object": <the object of GET /v1/objects>, "merged_into": int |
  null}``.
- ``resync`` (data ``{"reason": ...}``), then the stream ends: the client fell
  :data:`QUEUE_SIZE` changes behind (e.g. during a re-association that rewrites the map). It
  reconnects and reloads; an update is never skipped silently.
- a comment line every :data:`KEEPALIVE_S` seconds, so idle proxies keep the stream and a
  gone client is noticed.

Threads: the listener runs on the map writer's thread and only hands the change to the event
loop (``call_soon_threadsafe``); the JSON is built in the stream's coroutine. Queue policy per
stream: **bounded (QUEUE_SIZE), overflow ends the stream with ``resync``** (never blocks the
map writer, never drops silently). The listener is removed when the stream ends or the client
goes.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator
from typing import Final

from fastapi import APIRouter
from fastapi.responses import StreamingResponse

from wardmap.server.api.deps import ObjectMapDep
from wardmap.server.mapmessages import map_object
from wardmap.server.objectmap import ObjectChange, ObjectMap
from wardmap.shared.mapwire import object_to_wire

log = logging.getLogger(__name__)

__all__ = ["KEEPALIVE_S", "QUEUE_SIZE", "router", "update_event"]

QUEUE_SIZE: Final = 4096
"""Changes a stream may hold before it is told to resync."""
KEEPALIVE_S: Final = 15.0
"""Seconds between keep-alive comments on an idle stream."""

router = APIRouter()


def update_event(change: ObjectChange) -> bytes:
    """One ``update`` event (UTF-8 bytes, blank-line terminated) for a committed change."""
    data = {
        "kind": change.kind,
        "object": object_to_wire(map_object(change.record)),
        "merged_into": change.merged_into,
    }
    return b"event: update\ndata: " + json.dumps(data, separators=(",", ":")).encode() + b"\n\n"


def _event(name: str, data: dict[str, object]) -> bytes:
    return f"event: {name}\ndata: {json.dumps(data)}\n\n".encode()


class _Subscription:
    """One stream's bounded queue, filled from the map writer's thread; see the module docstring."""

    def __init__(self, loop: asyncio.AbstractEventLoop, size: int) -> None:
        self._loop = loop
        self.queue: asyncio.Queue[ObjectChange] = asyncio.Queue(size)
        """Changes in commit order."""
        self.overflowed = False
        """A change did not fit: the stream must resync (only touched on the loop's thread)."""

    def on_change(self, change: ObjectChange) -> None:
        """Object map listener (writer's thread): hand the change to the loop, nothing more."""
        # RuntimeError: the loop closed, the server is stopping and the stream is gone.
        with contextlib.suppress(RuntimeError):
            self._loop.call_soon_threadsafe(self._put, change)

    def _put(self, change: ObjectChange) -> None:
        if self.overflowed:
            return
        try:
            self.queue.put_nowait(change)
        except asyncio.QueueFull:
            self.overflowed = True  # the queue is full, so the stream's next get() returns at once


async def _stream(objects: ObjectMap) -> AsyncIterator[bytes]:
    sub = _Subscription(asyncio.get_running_loop(), QUEUE_SIZE)
    remove = objects.add_listener(sub.on_change)
    try:
        yield _event("ready", {})
        while True:
            if sub.overflowed:
                log.warning("an event stream fell %d changes behind: told to resync", QUEUE_SIZE)
                yield _event("resync", {"reason": f"more than {QUEUE_SIZE} changes behind"})
                return
            try:
                change = await asyncio.wait_for(sub.queue.get(), KEEPALIVE_S)
            except TimeoutError:
                yield b": keep-alive\n\n"
                continue
            yield update_event(change)
    finally:
        remove()


@router.get(
    "/v1/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}},
                     "description": "events `ready`, `update` (a map update as JSON), `resync`"}},
)
async def events(objects: ObjectMapDep) -> StreamingResponse:
    """The object map's changes as Server-Sent Events (docs/web.md)."""
    return StreamingResponse(
        _stream(objects),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
    )
