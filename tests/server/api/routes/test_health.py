"""``GET /healthz`` (``server/api/routes/health.py``)."""

from __future__ import annotations

import logging
import sqlite3
from types import SimpleNamespace
from typing import Any

import pytest
from fastapi.testclient import TestClient

from wardmap.server.api.deps import Services
from wardmap.server.api.readiness import check, public_reason
from wardmap.server.mapping import PipelineConfig
from wardmap.server.objectmap import ObjectMap
from wardmap.server.store import open_store


def test_healthz(keyframe_client: TestClient) -> None:
    """The liveness probe answers ok."""
    r = keyframe_client.get("/healthz")
    assert r.status_code == 200
    assert r.json() == {"status": "ok"}


def test_readyz_ok_while_the_store_can_write(keyframe_client: TestClient) -> None:
    """An API-only server on a writable store is ready."""
    r = keyframe_client.get("/readyz")
    assert r.status_code == 200
    assert r.json() == {"status": "ok"}


def test_readyz_503_while_another_process_holds_the_write_lock(
    keyframe_scene: Any, keyframe_client: TestClient, caplog: pytest.LogCaptureFixture
) -> None:
    """Another connection holds the database's write lock: not ready (503), with a short public
    reason that names no path, while the server logs the full reason (once for two probes); ready
    again once it lets go."""
    path = keyframe_scene.url.removeprefix("sqlite:///")
    other = sqlite3.connect(path, isolation_level=None)
    try:
        other.execute("BEGIN EXCLUSIVE")
        with caplog.at_level(logging.WARNING, logger="wardmap.server.api.readiness"):
            r = keyframe_client.get("/readyz")
            assert keyframe_client.get("/readyz").status_code == 503
        assert r.status_code == 503
        assert r.json() == {"status": "keyframe store locked"}
        logged = [rec.getMessage() for rec in caplog.records if "not ready" in rec.getMessage()]
        assert len(logged) == 1 and "locked" in logged[0], logged
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert keyframe_client.get("/readyz").status_code == 200


@pytest.mark.parametrize(
    ("why", "public"),
    [
        ("ingest is not running", "ingest is not running"),
        ("keyframe store cannot write: damaged: database disk image is malformed", "keyframe store damaged"),
        ("keyframe store /srv/map.db: no space left (disk or max_pages cap full)", "keyframe store full"),
        ("keyframe store cannot write: keyframe store /srv/map.db: database is locked",
         "keyframe store locked"),
        ("closed", "keyframe store closed"),
        ("keyframe store /srv/map.db: readiness probe: attempt to write a readonly database",
         "keyframe store cannot write"),
    ],
)
def test_readyz_public_reason_is_a_fixed_phrase(why: str, public: str) -> None:
    """Every full reason maps to one fixed phrase; none carries a path or SQLite's words."""
    assert public_reason(why) == public
    assert "/" not in public_reason(why)


class _Pipeline:
    """Stands in for the mapping stage in :func:`check` (only ``running``, ``counters`` and ``cfg``)."""

    def __init__(self, running: bool, backlog: int, bound: int) -> None:
        self._running, self._backlog = running, backlog
        self.cfg = PipelineConfig(ready_max_backlog=bound)

    def running(self) -> bool:
        return self._running

    def counters(self) -> Any:
        return SimpleNamespace(backlog=self._backlog)


@pytest.mark.parametrize(
    ("router", "pipeline", "public"),
    [
        (True, _Pipeline(True, 10, 10), "ok"),
        (False, _Pipeline(True, 0, 10), "zenoh router not connected"),
        (True, _Pipeline(False, 0, 10), "mapping stage not running"),
        (True, _Pipeline(True, 11, 10), "mapping backlog too long"),
    ],
)
def test_readiness_needs_the_router_and_a_mapping_stage_keeping_up(
    keyframe_scene: Any, router: bool, pipeline: _Pipeline, public: str
) -> None:
    """On a writable store: not ready without a router, with the mapping stage stopped, or with
    more keyframes waiting for it than ``ready_max_backlog`` (a backlog equal to it is ready); the
    full reason (for the log) maps to the fixed public phrase."""
    with open_store(keyframe_scene.url) as store:
        services = Services(store=store, objects=ObjectMap(store), pipeline=pipeline,  # type: ignore[arg-type]
                            router_connected=lambda: router)
        ok, why = check(services)
    assert ok == (public == "ok")
    assert (why if ok else public_reason(why)) == public


class _Standby:
    """A writer-lease role of a server whose lease another server holds (no stage here)."""

    pipeline = None

    def __init__(self, running: bool) -> None:
        self._running = running

    def running(self) -> bool:
        return self._running


@pytest.mark.parametrize(("running", "public"), [(True, "ok"), (False, "mapping stage not running")])
def test_a_standby_is_ready_while_its_lease_thread_runs(
    keyframe_scene: Any, running: bool, public: str
) -> None:
    """A standby (another server holds the writer lease and maps) stores keyframes and serves, so
    it is ready with no mapping stage of its own; not ready once its lease thread stopped (it
    could never take over)."""
    with open_store(keyframe_scene.url) as store:
        services = Services(store=store, objects=ObjectMap(store), mapping=_Standby(running),  # type: ignore[arg-type]
                            router_connected=lambda: True)
        ok, why = check(services)
    assert (why if ok else public_reason(why)) == public
