"""Object-map REST API latency: radius and category queries on a map of 10,000 objects.

Fills a temporary store with ``--objects`` objects (seeded random poses over a hospital
floor of ``--floor`` metres, every knowledge-graph class, one observation each by one of
four robots), starts the real server app (``MapServer(url).app`` under uvicorn, the settings of
``wardmap server``, bearer tokens required) in a child process on a free loopback port, and
times ``--queries`` requests of each kind with one keep-alive httpx client sending a ``read``
token (so each request includes the token check). Latency is client-side wall time
per request (send to full body read, JSON parsed); 100 warm-up requests are not counted.

    python bench/api.py [--objects 10000] [--queries 2000] [--radius 5] [--seed 0] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import git_rev, machine, write_section

from wardmap.server.objectmap import ObjectMap, ObjectQuery, ObjectState, Observation
from wardmap.server.store import open_store
from wardmap.server.tokens import create_token
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import yaw_transform

GOAL_P99_MS = 10.0
WARMUP = 100
ROBOTS = ("r1", "r2", "r3", "r4")


def fill(url: str, n: int, floor: tuple[float, float], seed: int) -> float:
    """Write ``n`` random objects with one observation each; returns the seconds it took."""
    rng = np.random.default_rng(seed)
    names = KnowledgeGraph.load().names
    objs, obs = [], []
    for i in range(n):
        oid = i + 1
        cat = names[i % len(names)]
        T = yaw_transform(
            rng.uniform(0, floor[0]),
            rng.uniform(0, floor[1]),
            rng.uniform(-np.pi, np.pi),
            rng.uniform(0.0, 2.0),
        )
        size = rng.uniform(0.2, 2.2, 3)
        rgb = rng.uniform(0, 255, 3)
        objs.append(
            ObjectState(
                oid,
                cat,
                float(rng.uniform(0.3, 1.0)),
                T,
                size,
                (float(rgb[0]), float(rgb[1]), float(rgb[2])),
            )
        )
        obs.append(
            Observation(
                oid,
                ROBOTS[i % len(ROBOTS)],
                "s1",
                i,
                1.7e9 + i,
                cat,
                0.8,
                np.array([10.0, 20.0, 110.0, 220.0]),
                T,
                size,
            )
        )
    t = time.perf_counter()
    with open_store(url) as store:
        ObjectMap(store).upsert(objs, obs)
    return time.perf_counter() - t


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def serve(url: str, port: int) -> None:
    """Child process: the server app on 127.0.0.1:port until terminated."""
    import uvicorn

    from wardmap.server.app import MapServer

    uvicorn.run(
        MapServer(url).app, host="127.0.0.1", port=port, log_config=None, access_log=False, lifespan="on"
    )


def wait_ready(client: httpx.Client, proc: subprocess.Popen[bytes], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"server exited with {proc.returncode}")
        try:
            if client.get("/healthz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    raise SystemExit("server not ready within 30 s")


def timed(client: httpx.Client, path: str, requests: list[dict[str, str]]) -> tuple[np.ndarray, float]:
    """Latencies (ms) of ``requests`` after the warm-up and the mean number of objects returned."""
    lat, hits = [], []
    for k, params in enumerate(requests):
        t = time.perf_counter()
        resp = client.get(path, params=params)
        body = resp.json()
        dt = time.perf_counter() - t
        if resp.status_code != 200:
            raise SystemExit(f"GET {path} {params} -> {resp.status_code}: {resp.text[:200]}")
        if k >= WARMUP:
            lat.append(dt * 1e3)
            hits.append(len(body.get("objects", ())))
    return np.array(lat), float(np.mean(hits))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--objects", type=int, default=10_000)
    ap.add_argument("--queries", type=int, default=2000)
    ap.add_argument("--radius", type=float, default=5.0, help="metres")
    ap.add_argument("--floor", type=float, nargs=2, default=(200.0, 100.0), metavar=("X_M", "Y_M"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--write", type=Path, default=None, help="write the table into this markdown file")
    ap.add_argument("--serve", nargs=2, metavar=("URL", "PORT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.serve:
        serve(args.serve[0], int(args.serve[1]))
        return 0

    floor = (float(args.floor[0]), float(args.floor[1]))
    rng = np.random.default_rng(args.seed + 1)
    names = KnowledgeGraph.load().names
    n = args.queries + WARMUP

    def centre() -> str:
        return f"{rng.uniform(0, floor[0]):.3f},{rng.uniform(0, floor[1]):.3f},1.0"

    kinds = {
        f"near + radius {args.radius:g} m": [
            {"near": centre(), "radius": str(args.radius)} for _ in range(n)
        ],
        "category (first 100)": [{"category": names[int(rng.integers(len(names)))]} for _ in range(n)],
        f"category + near + radius {args.radius:g} m": [
            {"category": names[int(rng.integers(len(names)))], "near": centre(), "radius": str(args.radius)}
            for _ in range(n)
        ],
        "robot + min_confidence (first 100)": [
            {"robot": ROBOTS[int(rng.integers(len(ROBOTS)))], "min_confidence": "0.9"} for _ in range(n)
        ],
    }
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="wardmap-bench-api-") as tmp:
        url = f"sqlite:///{Path(tmp) / 'map.db'}"
        fill_s = fill(url, args.objects, floor, args.seed)
        print(f"filled {args.objects} objects in {fill_s:.1f} s", file=sys.stderr)

        # In-process reference: the same radius query without HTTP.
        with open_store(url) as store:
            om = ObjectMap(store)
            direct = []
            for params in kinds[f"near + radius {args.radius:g} m"][:500]:
                x, y, z = (float(v) for v in params["near"].split(","))
                t = time.perf_counter()
                om.find(ObjectQuery(near=(x, y, z), radius_m=args.radius))
                direct.append((time.perf_counter() - t) * 1e3)

        with open_store(url) as store:
            token = create_token(store, "read", "bench").text
        port = free_port()
        proc = subprocess.Popen([sys.executable, __file__, "--serve", url, str(port)])
        try:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10.0,
                              headers={"Authorization": f"Bearer {token}"}) as client:
                wait_ready(client, proc)
                results = {name: timed(client, "/v1/objects", reqs) for name, reqs in kinds.items()}
                # Baseline: the HTTP stack alone (a route that does no work).
                results["GET /healthz (HTTP stack only)"] = timed(client, "/healthz", [{}] * n)
        finally:
            proc.terminate()
            proc.wait(15)

    rows = [
        "| query | requests | mean objects returned | p50 ms | p95 ms | p99 ms | max ms |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, (lat, hits) in results.items():
        p50, p95, p99 = np.percentile(lat, [50, 95, 99])
        rows.append(
            f"| `{name}` | {len(lat)} | {hits:.1f} | {p50:.2f} | {p95:.2f} | {p99:.2f} | {lat.max():.2f} |"
        )
    load_after = os.getloadavg()[0]
    d50, d99 = np.percentile(direct, [50, 99])
    radius_p99 = float(np.percentile(results[f"near + radius {args.radius:g} m"][0], 99))
    verdict = "met" if radius_p99 <= GOAL_P99_MS else "NOT met"
    write = f" --write {args.write}" if args.write else ""
    body = (
        "## Object map REST API (issue 6)\n\n"
        f"Command: `python bench/api.py --objects {args.objects} --queries {args.queries} "
        f"--radius {args.radius:g} --seed {args.seed}{write}`  \n"
        f"Machine: {machine()}; commit {git_rev()}; 1-min load average {load_before:.1f} before, "
        f"{load_after:.1f} after (other work on the machine inflates the tails).  \n"
        f"Map: {args.objects} objects over {floor[0]:g} m x {floor[1]:g} m, {len(names)} categories, "
        f"SQLite + R*Tree (written in {fill_s:.1f} s). Server: `MapServer(url).app` under uvicorn in a child "
        "process on 127.0.0.1; client: one keep-alive httpx client, sequential requests, "
        f"{WARMUP} warm-up requests per kind not counted.\n\n"
        + "\n".join(rows)
        + f"\n\nGoal p99 <= {GOAL_P99_MS:g} ms for the radius query: **{verdict}** ({radius_p99:.2f} ms). "
        f"The same radius query in-process (`ObjectMap.find`, no HTTP): p50 {d50:.2f} ms, p99 {d99:.2f} ms.\n"
    )
    print(body)
    if args.write is not None:
        write_section(args.write, "api", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
