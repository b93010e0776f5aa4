"""``wardmap server`` as a process: end-to-end ingest with a real router subprocess, a real
``wardmap server`` subprocess, and this test process as two robots publishing keyframes over
zenoh and listening for acks; start-up errors. Unit tests of the ingest: tests/server/test_ingest.py.

Sessions are zenoh clients on 127.0.0.1 with shared memory and multicast scouting off. The
test synchronises on ready lines, zenoh matching events and the ack queue, never on sleeps.
"""

from __future__ import annotations

import queue
import signal
import socket
import subprocess
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from factories import keyframe, walk
from peers import ALL_ACKS, matched_publisher, open_client
from procs import child_env as _env
from procs import free_port as _free_port
from procs import prometheus_samples, router_process, start, wardmap_cmd
from procs import stop as _stop

pytest.importorskip("zenoh")


from wardmap.shared import wire
from wardmap.shared.wire import AckMsg
from wardmap.shared.zenoh_config import keyframe_key

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]

READY_TIMEOUT_S = 20.0
EVENT_TIMEOUT_S = 10.0


@pytest.fixture
def router() -> Iterator[str]:
    """A ``wardmap router`` subprocess on a free loopback port, after its ready line; yields its endpoint."""
    with router_process(READY_TIMEOUT_S) as (_, endpoint):
        yield endpoint


@pytest.fixture
def server(router: str, tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """A ``wardmap server`` subprocess that requires tokens (the default); ``tmp_path/map.db``."""
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    cmd = wardmap_cmd("server", "--connect", router, "--db", f"sqlite:///{tmp_path / 'map.db'}",
                      "--http", f"127.0.0.1:{port}")
    proc = start(cmd, f"server ready: {url}", READY_TIMEOUT_S)
    try:
        yield proc, url
    finally:
        _stop(proc)


def _token(db: Path, scope: str) -> dict[str, str]:
    """The Authorization header of a token made by ``wardmap token create`` (a real process)."""
    made = subprocess.run(wardmap_cmd("token", "create", "--scope", scope, "--db", f"sqlite:///{db}"),
                          capture_output=True, text=True, timeout=30, env=_env())
    assert made.returncode == 0, made.stderr
    return {"Authorization": f"Bearer {made.stdout.strip()}"}


def _keyframes(robot: str, n: int) -> list[bytes]:
    base = keyframe(np.random.default_rng(sum(robot.encode())), robot_id=robot)  # seeded per robot
    return [wire.encode(m) for m in walk(base, n)]


def _garbage(valid: list[bytes], n: int) -> list[bytes]:
    """``n`` payloads that must all be rejected: random bytes, truncations, trailing junk."""
    rng = np.random.default_rng(7)
    out: list[bytes] = []
    for i in range(n):
        p = valid[i % len(valid)]
        kind = i % 3
        if kind == 0:
            out.append(rng.integers(0, 256, int(rng.integers(1, 2000)), dtype=np.uint8).tobytes())
        elif kind == 1:
            out.append(p[: int(rng.integers(1, len(p) - 1))])
        else:
            out.append(p + b"\x00junk")
    return out


def _collect(acks: queue.Queue[tuple[str, AckMsg]], n: int) -> list[tuple[str, AckMsg]]:
    got = []
    for _ in range(n):
        try:
            got.append(acks.get(timeout=EVENT_TIMEOUT_S))
        except queue.Empty:
            pytest.fail(f"only {len(got)} of {n} acks arrived: {Counter(a.status for _, a in got)}")
    return got


def test_ingest_stores_acks_dedups_and_rejects(
    server: tuple[subprocess.Popen[str], str], router: str, tmp_path: Path
) -> None:
    """50 keyframes of each of 2 robots are acked stored; 10 resent are acked duplicate; 200 garbage
    payloads (plus 10 keyframes on another robot's key) are acked rejected and counted; the API
    shows 50 keyframes per robot and the server stays healthy and exits 0 on SIGTERM."""
    proc, url = server
    headers = _token(tmp_path / "map.db", "read")
    acks: queue.Queue[tuple[str, AckMsg]] = queue.Queue()

    def on_ack(sample: Any) -> None:  # callbacks enqueue only
        acks.put((str(sample.key_expr), wire.decode_ack(sample.payload.to_bytes())))

    payloads = {r: _keyframes(r, 50) for r in ("r1", "r2")}
    with (
        open_client(router) as session,
        session.declare_subscriber(ALL_ACKS, on_ack),
        httpx.Client(base_url=url, timeout=10, headers=headers) as http,
    ):
        pubs = {robot: matched_publisher(session, keyframe_key(robot), EVENT_TIMEOUT_S) for robot in payloads}

        for i in range(50):
            for robot, pub in pubs.items():
                pub.put(payloads[robot][i])
        stored = _collect(acks, 100)
        assert {a.status for _, a in stored} == {"stored"}
        for robot in pubs:
            mine = sorted(a.seq for key, a in stored if a.robot_id == robot and key.endswith(f"/{robot}/ack"))
            assert mine == list(range(50))

        for i in range(10):
            pubs["r1"].put(payloads["r1"][i])
        dups = _collect(acks, 10)
        got = sorted((a.robot_id, a.seq, a.status) for _, a in dups)
        assert got == [("r1", i, "duplicate") for i in range(10)]

        garbage = _garbage(payloads["r1"], 200)
        for i, p in enumerate(garbage):
            pubs["r1" if i % 2 else "r2"].put(p)
        for i in range(10):  # valid bytes, wrong key: r1's keyframe on r2's key
            pubs["r2"].put(payloads["r1"][i])
        rejected = _collect(acks, 210)
        assert {a.status for _, a in rejected} == {"rejected"}
        assert acks.empty()

        metrics = prometheus_samples(http.get("/metrics").text)
        reasons = {k: v for k, v in metrics.items() if k.startswith("wardmap_rejections_total")}
        assert sum(reasons.values()) == 210, reasons
        assert metrics['wardmap_rejections_total{reason="robot_id mismatch"}'] == 10
        assert metrics["wardmap_keyframes_received_total"] == 320
        assert metrics["wardmap_keyframes_stored_total"] == 100
        assert metrics["wardmap_keyframes_duplicates_total"] == 10
        assert metrics["wardmap_robots"] == 2

        robots = {r["robot_id"]: r["keyframes"] for r in http.get("/v1/robots").json()["robots"]}
        assert robots == {"r1": 50, "r2": 50}
        assert http.get("/healthz").json() == {"status": "ok"}

    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=15) == 0
    assert proc.stderr is not None
    assert "Traceback" not in proc.stderr.read()


def test_server_bad_db_and_port_in_use_exit_1(router: str, tmp_path: Path) -> None:
    """A bad store URL and an HTTP port already taken each give exit 1 and one stderr line."""
    base = wardmap_cmd("server", "--connect", router)
    bad_db = subprocess.run(
        [*base, "--db", "mysql://x", "--http", f"127.0.0.1:{_free_port()}"],
        capture_output=True,
        text=True,
        timeout=30,
        env=_env(),
    )
    assert bad_db.returncode == 1
    assert bad_db.stderr.strip().splitlines() == [bad_db.stderr.strip()]
    assert "unknown store URL" in bad_db.stderr
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        args = ["--db", f"sqlite:///{tmp_path / 'm.db'}", "--http", f"127.0.0.1:{port}"]
        busy = subprocess.run([*base, *args], capture_output=True, text=True, timeout=30, env=_env())
    assert busy.returncode == 1
    assert busy.stdout == ""
    lines = busy.stderr.strip().splitlines()
    assert len(lines) == 1, busy.stderr
    assert "address already in use" in lines[0]


def test_rest_needs_a_token_created_while_the_server_runs(
    server: tuple[subprocess.Popen[str], str], tmp_path: Path
) -> None:
    """Without a token every data route is 401 (the probes are not); a ``read`` token made by
    ``wardmap token create`` while the server runs is accepted at once; after ``wardmap token
    revoke`` it is 401 again."""
    _, url = server
    with httpx.Client(base_url=url, timeout=10) as http:
        assert http.get("/healthz").status_code == 200
        for route in ("/v1/robots", "/metrics", "/v1/objects"):
            r = http.get(route)
            assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer"), route
        headers = _token(tmp_path / "map.db", "read")
        assert http.get("/v1/robots", headers=headers).status_code == 200
        token_id = headers["Authorization"].split("_")[1]
        revoked = subprocess.run(
            wardmap_cmd("token", "revoke", token_id, "--db", f"sqlite:///{tmp_path / 'map.db'}"),
            capture_output=True, text=True, timeout=30, env=_env())
        assert revoked.returncode == 0, revoked.stderr
        assert http.get("/v1/robots", headers=headers).status_code == 401


def test_insecure_loopback_is_refused_off_loopback(router: str, tmp_path: Path) -> None:
    """``--insecure-loopback`` with ``--http 0.0.0.0:PORT`` exits 1 with one line saying why."""
    cmd = wardmap_cmd("server", "--connect", router, "--db", f"sqlite:///{tmp_path / 'm.db'}",
                      "--http", f"0.0.0.0:{_free_port()}", "--insecure-loopback")
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=30, env=_env())
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--insecure-loopback refused" in lines[0], done.stderr
