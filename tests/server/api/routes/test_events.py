"""``GET /v1/events`` (``server/api/routes/events.py``): the object map's changes as
Server-Sent Events, read from the real app under uvicorn with a streaming HTTP client, and
the stream's overflow policy on its own."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import webscene

from wardmap.server.api.routes import events
from wardmap.server.objectmap import ObjectChange, ObjectMap, ObjectState
from wardmap.server.store import open_store
from wardmap.shared.se3 import yaw_transform


def _state(oid: int, category: str = "sink", x: float = 1.0) -> ObjectState:
    return ObjectState(oid, category, 0.8, yaw_transform(x, 2.0, 0.0, 0.9), np.array([0.6, 0.5, 0.3]))


def _events(lines: Iterator[str]) -> Iterator[tuple[str, str]]:
    """(event, data) pairs of a text/event-stream, comments skipped."""
    name, data = "message", []
    for line in lines:
        if line == "":
            if data or name != "message":
                yield name, "\n".join(data)
            name, data = "message", []
        elif line.startswith("event:"):
            name = line[6:].strip()
        elif line.startswith("data:"):
            data.append(line[5:].lstrip(" "))


def test_stream_sends_ready_then_every_change_in_order(tmp_path: Path) -> None:
    """After ``ready``, two creates, an update (a new category) and a merge written by the map
    arrive as ``update`` events in commit order, each with the whole object as ``GET
    /v1/objects`` shows it; the stream is text/event-stream and not cached."""
    url = f"sqlite:///{tmp_path / 'map.db'}"
    token = webscene.read_token(url)
    with (webscene.live_server(url) as (base, root),
          httpx.Client(base_url=base, timeout=10, headers={"Authorization": f"Bearer {token}"}) as http):
        assert httpx.get(f"{base}/v1/events", timeout=10).status_code == 401  # the stream needs a token
        with http.stream("GET", "/v1/events") as resp:
            assert resp.status_code == 200
            assert resp.headers["content-type"].startswith("text/event-stream")
            assert resp.headers["cache-control"] == "no-store"
            stream = _events(resp.iter_lines())
            assert next(stream) == ("ready", "{}")
            assert root.services is not None
            objects = root.services.objects
            objects.upsert([_state(1), _state(2, "cup", 3.0)])
            objects.upsert([_state(2, "chair", 3.0)])
            objects.delete(1, merged_into=2)
            got = [next(stream) for _ in range(4)]
        listed = http.get("/v1/objects").json()["objects"]
    assert [name for name, _ in got] == ["update"] * 4
    updates = [json.loads(data) for _, data in got]
    assert [(u["kind"], u["object"]["object_id"], u["merged_into"]) for u in updates] == [
        ("created", 1, None), ("created", 2, None), ("updated", 2, None), ("deleted", 1, 2)]
    assert updates[2]["object"]["category"] == "chair"
    assert listed == [updates[2]["object"]]  # the same object message as the REST list


def test_stream_that_falls_behind_is_told_to_resync(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With room for 2 changes, three changes reach the stream before it reads one: it sends
    the first, then ``resync`` (instead of skipping the third) and ends, removing its listener."""
    monkeypatch.setattr(events, "QUEUE_SIZE", 2)
    with open_store(f"sqlite:///{tmp_path / 'map.db'}") as store:
        objects = ObjectMap(store)
        subscribed: list[int] = []  # +1 per add_listener, -1 per removal
        add = objects.add_listener

        def counted_add(callback: Callable[[ObjectChange], None]) -> Callable[[], None]:
            remove = add(callback)
            subscribed.append(1)
            return lambda: (subscribed.append(-1), remove())[1]

        monkeypatch.setattr(objects, "add_listener", counted_add)

        async def run() -> list[bytes]:
            stream = events._stream(objects)
            out = [await anext(stream)]  # ready: subscribed
            objects.upsert([_state(1), _state(2), _state(3)])  # handed to the loop, not yet queued
            out += [chunk async for chunk in stream]
            return out

        chunks = asyncio.run(run())
    assert chunks[0] == b"event: ready\ndata: {}\n\n"
    assert chunks[1].startswith(b"event: update\n") and b'"object_id":1,' in chunks[1]
    assert chunks[2] == b'event: resync\ndata: {"reason": "more than 2 changes behind"}\n\n'
    assert len(chunks) == 3 and subscribed == [1, -1]
