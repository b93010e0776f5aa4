"""``wardmap server --db postgresql://...`` end to end: a real router subprocess, a real
``wardmap server`` subprocess on a database of the session's PostgreSQL cluster
(tests/pgcluster.py) reached as a role that must give a password, which comes from
``--db-password-file``; this test process publishes two robots' keyframes over zenoh, waits
for the acks and queries the REST API with a token made by ``wardmap token create``.
SQLite's end-to-end tests: tests/integration/test_server_cmd.py.
"""

from __future__ import annotations

import queue
import subprocess
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pgcluster
import pytest
from factories import keyframe, walk
from peers import ALL_ACKS, matched_publisher, open_client
from procs import child_env, free_port, prometheus_samples, router_process, start, stop, wardmap_cmd

pytest.importorskip("zenoh")
pytest.importorskip("psycopg")

from wardmap.shared import wire
from wardmap.shared.wire import AckMsg
from wardmap.shared.zenoh_config import keyframe_key

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

READY_TIMEOUT_S = 30.0
EVENT_TIMEOUT_S = 15.0
MAPPING_TIMEOUT_S = 60.0


@pytest.fixture
def database(pg_cluster: pgcluster.Cluster, tmp_path: Path) -> tuple[str, Path]:
    """A new database's URL for the password role, and the password file for it."""
    url = pg_cluster.url(pg_cluster.new_database(), user=pgcluster.PASSWORD_ROLE)
    secret = tmp_path / "db-password"
    secret.write_text(pgcluster.PASSWORD + "\n")
    secret.chmod(0o600)
    return url, secret


def test_server_on_postgres_stores_acks_and_serves(
    database: tuple[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    """20 keyframes of each of 2 robots are acked stored, 5 resent are acked duplicate; the REST
    API (token from ``wardmap token create`` on the same database) lists both robots with 20
    keyframes, pages r1's keyframes in stamp order, and says ready; the server exits on SIGTERM."""
    url, secret = database
    monkeypatch.delenv("WARDMAP_DB_PASSWORD", raising=False)
    monkeypatch.setenv("PGPASSFILE", "/nonexistent")  # the password file option is the only source
    made = subprocess.run(
        wardmap_cmd("token", "create", "--scope", "read", "--db", url, "--db-password-file", str(secret)),
        capture_output=True, text=True, timeout=60, env=child_env(),
    )
    assert made.returncode == 0, made.stderr
    headers = {"Authorization": f"Bearer {made.stdout.strip()}"}
    port = free_port()
    api = f"http://127.0.0.1:{port}"
    with router_process(READY_TIMEOUT_S) as (_, router):
        _serve_and_check(router, url, secret, port, api, headers)


def _serve_and_check(
    router: str, url: str, secret: Path, port: int, api: str, headers: dict[str, str]
) -> None:
    proc = start(
        wardmap_cmd("server", "--connect", router, "--db", url, "--db-password-file", str(secret),
                    "--http", f"127.0.0.1:{port}"),
        f"server ready: {api}", READY_TIMEOUT_S,
    )
    try:
        acks: queue.Queue[AckMsg] = queue.Queue()

        def on_ack(sample: Any) -> None:  # callbacks enqueue only
            acks.put(wire.decode_ack(sample.payload.to_bytes()))

        payloads = {
            r: [wire.encode(m) for m in walk(keyframe(np.random.default_rng(i), robot_id=r), 20)]
            for i, r in enumerate(("r1", "r2"))
        }

        def collect(n: int) -> list[AckMsg]:
            got = []
            for _ in range(n):
                try:
                    got.append(acks.get(timeout=EVENT_TIMEOUT_S))
                except queue.Empty:
                    pytest.fail(f"only {len(got)} of {n} acks arrived: {[a.status for a in got]}")
            return got

        with (
            open_client(router) as session,
            session.declare_subscriber(ALL_ACKS, on_ack),
            httpx.Client(base_url=api, timeout=10, headers=headers) as http,
        ):
            pubs = {r: matched_publisher(session, keyframe_key(r), EVENT_TIMEOUT_S) for r in payloads}
            for i in range(20):
                for robot, pub in pubs.items():
                    pub.put(payloads[robot][i])
            stored = collect(40)
            assert sorted((a.robot_id, a.seq, a.status) for a in stored) == sorted(
                (r, s, "stored") for r in payloads for s in range(20))
            for i in range(5):
                pubs["r1"].put(payloads["r1"][i])
            assert sorted((a.seq, a.status) for a in collect(5)) == [(i, "duplicate") for i in range(5)]

            robots = {r["robot_id"]: r["keyframes"] for r in http.get("/v1/robots").json()["robots"]}
            assert robots == {"r1": 20, "r2": 20}
            page = http.get("/v1/keyframes", params={"robot": "r1", "limit": 50}).json()
            stamps = [k["stamp"] for k in page["keyframes"]]
            assert len(stamps) == 20 and stamps == sorted(stamps)
            ready = http.get("/readyz")
            assert ready.status_code == 200, ready.text

            # The mapping stage and the back-end read the keyframes back and write their rows.
            deadline = time.monotonic() + MAPPING_TIMEOUT_S
            while True:
                metrics = prometheus_samples(http.get("/metrics").text)
                done = [metrics.get(f"wardmap_{s}_keyframes_total", 0) for s in ("mapping", "backend")]
                if done == [40, 40] or time.monotonic() > deadline:
                    break
                time.sleep(0.2)  # polling the server's own progress counters, bounded by the deadline
            assert done == [40, 40], metrics
            assert metrics.get("wardmap_mapping_failures_total", 0) == 0
            assert metrics.get("wardmap_backend_failures_total", 0) == 0
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    finally:
        stop(proc)
    assert proc.returncode == 0, err[-3000:]
    assert "Traceback" not in err and "ERROR" not in err, err[-3000:]
