"""``GET /metrics`` (``server/api/routes/metrics.py``) over the keyframe scene of ``conftest.py``."""

from __future__ import annotations

import time
from typing import Any

from fastapi.testclient import TestClient


def _samples(text: str) -> dict[str, float]:
    samples = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            samples[name] = float(value)
    return samples


def test_metrics(keyframe_client: TestClient) -> None:
    """Prometheus text carries the ingest counters (0 without ingest), rejections by reason, robots
    and the map's objects; no mapping counters without a mapping stage."""
    r = keyframe_client.get("/metrics")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain")
    samples = _samples(r.text)
    assert samples["wardmap_keyframes_received_total"] == 0
    assert samples["wardmap_keyframes_stored_total"] == 0
    assert samples["wardmap_keyframes_duplicates_total"] == 0
    assert samples["wardmap_ingest_queue_depth"] == 0
    assert samples["wardmap_robots"] == 2
    assert samples['wardmap_rejections_total{reason="wire: payload"}'] == 2
    assert samples['wardmap_rejections_total{reason="odd \\"reason\\""}'] == 1
    assert samples['wardmap_map_objects{confirmed="true"}'] == 0
    for name in ("wardmap_keyframes_received_total", "wardmap_rejections_total", "wardmap_robots"):
        assert f"# TYPE {name} " in r.text
    assert not any(name.startswith("wardmap_mapping_") for name in samples)


def test_metrics_reads_the_counters_at_each_scrape(keyframe_client: TestClient) -> None:
    """A rejection counted after the first scrape shows in the next one (the collector reads the
    store at scrape time, it keeps no copy)."""
    before = _samples(keyframe_client.get("/metrics").text)
    keyframe_client.app.state.services.store.count_rejection("wire: payload")  # type: ignore[attr-defined]
    after = _samples(keyframe_client.get("/metrics").text)
    key = 'wardmap_rejections_total{reason="wire: payload"}'
    assert (before[key], after[key]) == (2, 3)


def test_metrics_time_each_route_by_its_template(keyframe_client: TestClient) -> None:
    """REST requests are timed per route template, never per raw path: two robots' trajectories
    are one series, a path no route matches is ``unmatched``; the build info names the version and
    the python."""
    for robot in ("r1", "r2"):
        keyframe_client.get(f"/v1/robots/{robot}/trajectory")
    keyframe_client.get("/healthz")
    keyframe_client.get("/no/such/path/at/all")
    text = keyframe_client.get("/metrics").text
    samples = _samples(text)
    count = 'wardmap_http_request_seconds_count{method="GET",route="/v1/robots/{robot_id}/trajectory"}'
    assert samples[count] == 2
    assert samples['wardmap_http_request_seconds_count{method="GET",route="/healthz"}'] == 1
    assert samples['wardmap_http_request_seconds_count{method="GET",route="unmatched"}'] == 1
    assert not any("r1" in name or "/no/such" in name for name in samples)
    assert "# TYPE wardmap_http_request_seconds histogram" in text
    build = next(name for name in samples if name.startswith("wardmap_build_info"))
    assert 'python="3.' in build and 'version="' in build and 'git="' in build


def test_the_retention_job_runs_in_the_server_and_is_counted(keyframe_scene: Any, token_headers: Any) -> None:
    """A server with ``[store] image_retention = "60s"`` over the keyframe scene (received in
    2024): its job erases every image at start, and /metrics counts them."""
    from wardmap.server.app import MapServer
    from wardmap.server.retention import RetentionConfig

    server = MapServer(keyframe_scene.url, retention=RetentionConfig(image_retention="60s"))
    with TestClient(server.app, headers=token_headers(keyframe_scene.url)) as client:
        deadline = time.monotonic() + 30.0
        total = keyframe_scene.n_r1 + keyframe_scene.n_r2
        while (erased := _samples(client.get("/metrics").text).get("wardmap_images_erased_total", 0)) < total:
            assert time.monotonic() < deadline, f"{erased} of {total} images erased in 30 s"
            time.sleep(0.05)
        assert erased == total
        assert client.get("/v1/keyframes/r2/s1/0/image").status_code == 410
