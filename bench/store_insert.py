"""Keyframe insert latency of the map store backends: the time ingest waits before it may ack.

For each ``--writers`` count and ``--db`` URL (a SQLite file or PostgreSQL database, empty at
first; the PostgreSQL password as for ``wardmap server``: ``WARDMAP_DB_PASSWORD`` or
``~/.pgpass``), that many threads, each with its own store handle (as several ingest threads or
servers), insert ``--keyframes`` new keyframes (a 320x240 noise JPEG, 160x120 depth, 200
keypoints) each; every insert returns after its commit. Reports sustained inserts/s over all writers and the
per-insert latency (p50, p99, max). A durable measurement needs the database's own durability
on (SQLite: ``synchronous = FULL``, always; PostgreSQL: ``fsync`` and ``synchronous_commit``
on, as a default server has them).

    python bench/store_insert.py --db sqlite:////tmp/b.db --db postgresql://u@127.0.0.1:5432/b \
        [--keyframes 200] [--writers 1 4] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import git_rev, machine, publish

from wardmap.server.store import open_store
from wardmap.shared import wire
from wardmap.shared.wire import Intrinsics, KeyframeMsg, Keypoints, PackedRaster


def _keyframes(robot: str, n: int) -> list[tuple[KeyframeMsg, bytes]]:
    """``n`` valid keyframes of ``robot`` (seq 0..n-1) with their wire bytes: a 320x240 noise JPEG
    (quality 85), 160x120 depth, 200 keypoints (seeded per robot)."""
    import cv2

    rng = np.random.default_rng(sum(robot.encode()))
    ok, jpeg = cv2.imencode(".jpg", rng.integers(0, 256, (240, 320, 3), dtype=np.uint8),
                            [cv2.IMWRITE_JPEG_QUALITY, 85])
    if not ok:
        raise RuntimeError("OpenCV could not encode the bench image")
    k = 200
    base = KeyframeMsg(
        robot_id=robot, session_id="s1", seq=0, stamp=1.7e9, T_odom_camera=np.eye(4), pose_source="rgb",
        keypoints=Keypoints(
            uv=(rng.random((k, 2)) * [319, 239]).astype(np.float32),
            octave=rng.integers(0, 8, k).astype(np.int8),
            angle_deg=(rng.random(k) * 360).astype(np.float32),
            depth_m=rng.uniform(0.3, 6.0, k).astype(np.float32),
            descriptors=rng.integers(0, 256, (k, 32), dtype=np.uint8)),
        rgb_jpeg=jpeg.tobytes(),
        depth=PackedRaster(*wire.encode_depth(rng.uniform(0.3, 8.0, (120, 160)).astype(np.float32))),
        intrinsics=Intrinsics(320, 240, 250.0, 250.0, 159.5, 119.5, (0.0, 0.0, 0.0, 0.0, 0.0), 5000.0),
    )
    msgs = [replace(base, seq=i, stamp=base.stamp + i) for i in range(n)]
    return [(m, wire.encode(m)) for m in msgs]


def run(url: str, n: int, writers: int) -> dict[str, float]:
    """Insert ``n`` keyframes from each of ``writers`` threads; rate and latency quantiles."""
    work = [_keyframes(f"w{writers}r{w}", n) for w in range(writers)]  # new keys in every run
    latencies: list[list[float]] = [[] for _ in range(writers)]
    start = threading.Barrier(writers + 1)

    def write(w: int) -> None:
        with open_store(url) as store:
            start.wait()
            for msg, data in work[w]:
                t0 = time.perf_counter()
                if store.insert(msg, data, time.time()) != "stored":
                    raise RuntimeError(f"{url}: keyframe {msg.seq} of {msg.robot_id} was not new")
                latencies[w].append(time.perf_counter() - t0)

    threads = [threading.Thread(target=write, args=(w,)) for w in range(writers)]
    for t in threads:
        t.start()
    start.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    ms = np.array([x for lat in latencies for x in lat]) * 1000.0
    if len(ms) != n * writers:
        raise RuntimeError(f"{url}: only {len(ms)} of {n * writers} inserts finished (see the thread errors)")
    return {"rate": len(ms) / wall, "p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
            "max": float(ms.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--db", action="append", required=True, metavar="URL", help="an empty store (repeatable)")
    ap.add_argument("--keyframes", type=int, default=200, help="per writer (default: %(default)s)")
    ap.add_argument("--writers", type=int, nargs="+", default=[1, 4],
                    help="concurrent writer threads, one run per number (default: %(default)s)")
    ap.add_argument("--write", type=Path, metavar="FILE", help="also put the table in this BENCHMARKS.md")
    args = ap.parse_args()
    size_kb = len(_keyframes("r0", 1)[0][1]) / 1000
    rows = []
    for writers in args.writers:
        for url in args.db:
            r = run(url, args.keyframes, writers)
            backend = url.split(":", 1)[0]
            rows.append(f"| {backend} | {writers} | {args.keyframes * writers} | {r['rate']:.0f} | "
                        f"{r['p50']:.2f} | {r['p99']:.2f} | {r['max']:.1f} |")
    body = "\n".join([
        "## Map store: keyframe insert (ack after commit)", "",
        f"`python bench/store_insert.py --keyframes {args.keyframes} "
        f"--writers {' '.join(map(str, args.writers))} --db ...` at "
        f"{git_rev()}; {machine()}. Keyframes of {size_kb:.0f} KB; every insert committed before it returns; "
        "PostgreSQL 15 on the same host over TCP loopback with fsync and synchronous_commit on. "
        "Backends run one after the other in one process, so compare them within one table; on a shared "
        "host the same table varies by up to 4x between runs.", "",
        "| backend | writers | inserts | inserts/s | p50 ms | p99 ms | max ms |",
        "|---|---:|---:|---:|---:|---:|---:|",
        *rows,
    ])
    publish(body, args.write, "store-insert")


if __name__ == "__main__":
    main()
