"""Bounded cost (issue 39): what a raster bomb costs the wire decoder, and keep-alive latency of
the map server's HTTP socket with and without TCP_NODELAY.

1. Raster bomb: a 300 KB keyframe whose colour, depth and thermal headers declare 8192x8192
   (``tests/factories.py`` ``raster_bomb``), decoded ``--bombs`` times with ``wire.decode``:
   time per decode and the peak of traced allocations (tracemalloc).
2. A valid 640x480 keyframe (random colour, full-size random depth, 160x120 thermal):
   ``wire.decode_keyframe`` time.
3. Keep-alive: ``run_server`` (API only, a ``read`` token, a router on a thread) on 127.0.0.1,
   one keep-alive httpx client, ``--requests`` sequential requests of ``/healthz`` and
   ``/v1/categories`` after 50 warm-up ones; once with the server's socket as ``_bind`` makes
   it, once with a socket made as before issue 39 (protocol 0, so asyncio never set
   TCP_NODELAY).

    python bench/hostile_input.py [--bombs 5] [--requests 500] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import tempfile
import threading
import time
import tracemalloc
from pathlib import Path

import cv2
import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "tests"))
from _report import git_rev, machine, publish  # noqa: E402
from factories import raster_bomb  # noqa: E402
from peers import router_on_thread  # noqa: E402

import wardmap.server.app as app_module  # noqa: E402
from wardmap.server.store import open_store  # noqa: E402
from wardmap.server.tokens import create_token  # noqa: E402
from wardmap.shared import wire  # noqa: E402
from wardmap.shared.errors import WireError  # noqa: E402

WARMUP = 50


def bomb_cost(n: int) -> tuple[int, float, float]:
    """``(payload bytes, mean ms per decode, peak traced MiB)`` over ``n`` decodes of a bomb."""
    payload = raster_bomb(np.random.default_rng(0))
    times = []
    tracemalloc.start()
    try:
        for _ in range(n):
            t = time.perf_counter()
            try:
                wire.decode(payload)
            except WireError:
                pass
            else:
                raise SystemExit("the raster bomb was accepted")
            times.append(time.perf_counter() - t)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return len(payload), 1e3 * float(np.mean(times)), peak / 2**20


def valid_cost(n: int = 100) -> tuple[int, float]:
    """``(payload bytes, mean ms)`` of ``decode_keyframe`` on a valid 640x480 keyframe."""
    rng = np.random.default_rng(0)
    rgb = cv2.imencode(".jpg", rng.integers(0, 255, (480, 640, 3), dtype=np.uint8))[1].tobytes()
    kp = wire.Keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.int8), np.zeros(0, np.float32),
                        np.zeros(0, np.float32), np.zeros((0, 32), np.uint8))
    msg = wire.KeyframeMsg(
        "r1", "s1", 1, 1e9, np.eye(4), "rgb", kp, rgb,
        wire.PackedRaster(*wire.encode_depth((1.0 + rng.random((480, 640))).astype(np.float32))),
        calib_ref="bench",
        thermal=wire.PackedRaster(*wire.encode_thermal((300 + rng.random((120, 160))).astype(np.float32))),
    )
    payload = wire.encode(msg)
    for _ in range(5):
        wire.decode_keyframe(payload)
    t = time.perf_counter()
    for _ in range(n):
        wire.decode_keyframe(payload)
    return len(payload), 1e3 * (time.perf_counter() - t) / n


def _old_bind(host: str, port: int, *, loopback_only: bool = False) -> socket.socket:
    """The HTTP socket as made before issue 39: protocol 0, no TCP_NODELAY."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(128)
    sock.set_inheritable(True)
    return sock


def keepalive(n: int, old_socket: bool) -> dict[str, np.ndarray]:
    """Latencies (ms) of ``n`` keep-alive requests per path through ``run_server``."""
    bind = app_module._bind
    if old_socket:
        app_module._bind = _old_bind  # type: ignore[assignment]
    try:
        with router_on_thread() as endpoint, tempfile.TemporaryDirectory(prefix="wardmap-bench-") as tmp:
            url = f"sqlite:///{Path(tmp) / 'map.db'}"
            with open_store(url) as store:
                token = create_token(store, "read", "bench").text
            stop, ready, urls = threading.Event(), threading.Event(), []
            worker = threading.Thread(
                target=app_module.run_server, args=([endpoint], url, "127.0.0.1", 0),
                kwargs={"stop": stop, "on_ready": lambda u: (urls.append(u), ready.set())}, daemon=True)
            worker.start()
            if not ready.wait(60):
                raise SystemExit("server not ready within 60 s")
            out = {}
            try:
                with httpx.Client(base_url=urls[0], headers={"Authorization": f"Bearer {token}"}) as client:
                    for path in ("/healthz", "/v1/categories"):
                        lat = []
                        for k in range(n + WARMUP):
                            t = time.perf_counter()
                            resp = client.get(path)
                            resp.read()
                            if resp.status_code != 200:
                                raise SystemExit(f"GET {path} -> {resp.status_code}")
                            if k >= WARMUP:
                                lat.append((time.perf_counter() - t) * 1e3)
                        out[path] = np.array(lat)
            finally:
                stop.set()
                worker.join(30)
            return out
    finally:
        app_module._bind = bind  # type: ignore[assignment]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bombs", type=int, default=5)
    ap.add_argument("--requests", type=int, default=500)
    ap.add_argument("--write", type=Path, default=None, help="write the table into this markdown file")
    args = ap.parse_args()

    load_before = os.getloadavg()[0]
    bomb_bytes, bomb_ms, bomb_mib = bomb_cost(args.bombs)
    valid_bytes, valid_ms = valid_cost()
    rows = [
        "| case | figure |",
        "|---|---|",
        f"| raster bomb ({bomb_bytes / 1e3:.0f} KB declaring 8192x8192 colour, depth, thermal): refused in | "
        f"{bomb_ms:.2f} ms per decode, peak {bomb_mib:.2f} MiB traced |",
        f"| valid 640x480 keyframe ({valid_bytes / 1e3:.0f} KB, full-size random depth): `decode_keyframe` | "
        f"{valid_ms:.2f} ms |",
    ]
    for old in (False, True):
        what = "socket as before issue 39 (no TCP_NODELAY)" if old else "`_bind`'s socket (TCP_NODELAY)"
        for path, lat in keepalive(args.requests, old).items():
            rows.append(f"| keep-alive `GET {path}`, {what}, {len(lat)} requests | p50 "
                        f"{np.percentile(lat, 50):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms |")
    body = "\n".join([
        "## Bounded cost of hostile input (issue 39)",
        "",
        f"Command: `python bench/hostile_input.py --bombs {args.bombs} --requests {args.requests} "
        "--write BENCHMARKS.md`  ",
        f"Machine: {machine()}; commit {git_rev()}; 1-min load average {load_before:.1f} before, "
        f"{os.getloadavg()[0]:.1f} after (a shared host: upper bounds).",
        "",
        *rows,
        "",
        "The server's peak RSS under ten raster bombs and forty 50 MB payloads is measured by "
        "`tests/integration/test_failures.py::test_raster_bombs_and_a_50mb_flood_keep_the_server_small` "
        "(bound 600 MiB).",
    ])
    publish(body, args.write, "hostile_input")
    return 0


if __name__ == "__main__":
    sys.exit(main())
