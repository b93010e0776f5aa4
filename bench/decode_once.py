"""CPU per keyframe through ingest, back-end and mapping stage: decoded once vs in every stage.

A short simulated run (``--scenario``, ``--seed``, ``--frames``; generated under ``--data`` and
cached) is tracked by the edge frontend offline (``wardmap.tools.keyframes``: the messages a
robot sends, oracle labels, people blanked). Each mode then runs on a fresh SQLite store in one
process: the keyframes go through ingest's calls (``decode_keyframe``, ``store.insert``, the
decoded message handed to the :class:`~wardmap.server.decoded.DecodedCache`, as
``server/ingest.py`` does after the commit; no Zenoh) while the back-end and mapping stage run
in their threads (the packaged segmentation model), until the mapping stage is idle. Reported:
process CPU seconds (all threads) over that span per keyframe, and the cache's counters.

Modes: ``each stage decodes`` is ``DecodedCache(max_bytes=0)``: nothing is kept, so the back-end
and the mapping stage each decode the stored payload and its JPEG and depth again (what the
server did before the cache); ``decoded once`` is the server's default cache. A second table
times the decode calls alone on the same keyframes.

One core: OpenCV, numba, BLAS and the segmenter use one thread.

    python bench/decode_once.py [--data out/bench_data] [--frames 120] [--repeat 2] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _one_core  # noqa: F401  (one thread per library, before numba and OpenCV load)
import cv2
from _report import git_rev, machine, publish

from wardmap.server.backend.stage import BackendStage
from wardmap.server.decoded import DEFAULT_MAX_BYTES, DecodedCache, decode_images, keyframe_key
from wardmap.server.mapping import MapPipeline, PipelineConfig
from wardmap.server.objectmap import ObjectMap
from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.keyframe import decode_keyframe_images
from wardmap.server.perception.models import Segmenter, make_segmenter
from wardmap.server.store import open_store
from wardmap.shared import wire
from wardmap.shared.wire import decode_keyframe

MODES = (("each stage decodes", 0), ("decoded once", DEFAULT_MAX_BYTES))


def keyframe_payloads(data: Path, scenario: str, seed: int, frames: int) -> list[bytes]:
    """The wire payloads of the edge's keyframes of a simulated one-robot run (generated when
    missing)."""
    from wardmap.sim.runner import generate
    from wardmap.tools.keyframes import dataset_keyframes

    path = data / f"{scenario}_{seed}_{frames}"
    if not (path / "DONE").is_file():
        generate(scenario, seed, path, frames=frames, overwrite=True)
        (path / "DONE").write_text("")
    msgs = dataset_keyframes(path, robot_id="r1", session_id="bench", labels="oracle")
    return [wire.encode(m) for m in msgs]


def run(payloads: list[bytes], max_bytes: int, segmenter: Segmenter) -> dict[str, float]:
    """One mode on a fresh store: process CPU seconds per keyframe and the cache's counters."""
    with tempfile.TemporaryDirectory() as tmp:
        store = open_store(f"sqlite:///{tmp}/map.db")
        try:
            cache = DecodedCache(max_bytes)
            backend = BackendStage(store, decoded=cache)
            pipeline = MapPipeline(store, ObjectMap(store), segmenter=segmenter, backend=backend,
                                   config=PipelineConfig(poll_s=0.05))
            pipeline.start()
            try:
                cpu0, wall0 = time.process_time(), time.perf_counter()
                for payload in payloads:  # ingest's calls (server/ingest.py, Ingest._process)
                    msg = decode_keyframe(payload)
                    if store.insert(msg, payload, time.time()) == "stored":
                        cache.put(keyframe_key(msg), msg, len(payload))
                if not pipeline.wait_idle(1800):
                    raise SystemExit("the mapping stage did not finish within 30 min")
                cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
            finally:
                pipeline.stop()
            c = cache.counters()
            if pipeline.counters().processed != len(payloads):
                raise SystemExit(f"mapping processed {pipeline.counters().processed} of {len(payloads)}")
        finally:
            store.close()
    n = len(payloads)
    return {"cpu_ms": 1e3 * cpu / n, "wall_ms": 1e3 * wall / n, "hits": c.hits, "from_store": c.from_store,
            "images_decoded": c.images_decoded, "evicted": c.evicted}


def decode_costs(payloads: list[bytes], repeat: int = 3) -> dict[str, float]:
    """Median milliseconds per keyframe of each decode call, over ``repeat`` passes."""
    def timed(fn: object) -> float:
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            for p in payloads:
                fn(p)  # type: ignore[operator]
            times.append((time.perf_counter() - t0) / len(payloads))
        return 1e3 * statistics.median(times)

    msgs = {p: decode_keyframe(p) for p in payloads}
    images = {p: decode_images(msgs[p]) for p in payloads}
    return {
        "decode_keyframe (message)": timed(decode_keyframe),
        "decode_images (JPEG + depth)": timed(lambda p: decode_images(msgs[p])),
        "perception's rasters from decoded images (depth upsampled)":
            timed(lambda p: decode_keyframe_images(msgs[p], images[p])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("out/bench_data"))
    ap.add_argument("--scenario", default="aisle_slow_1")
    ap.add_argument("--seed", type=int, default=2001)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--repeat", type=int, default=2,
                    help="runs of each mode, alternating (default: %(default)s)")
    ap.add_argument("--write", type=Path, metavar="FILE", help="also put the tables in this BENCHMARKS.md")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    payloads = keyframe_payloads(args.data, args.scenario, args.seed, args.frames)
    segmenter = make_segmenter("model", PerceptionConfig(), threads=1)
    rows = []
    cpu: list[tuple[str, float]] = []
    for i in range(args.repeat):
        for name, max_bytes in MODES:
            r = run(payloads, max_bytes, segmenter)
            cpu.append((name, r["cpu_ms"]))
            rows.append(f"| {name} | {i + 1} | {r['cpu_ms']:.1f} | {r['wall_ms']:.1f} | {r['hits']} | "
                        f"{r['from_store']} | {r['images_decoded']} | {r['evicted']} |")
            print(rows[-1], flush=True)
    costs = decode_costs(payloads)
    medians = {name: statistics.median(c for m, c in cpu if m == name) for name, _ in MODES}
    saved = 2 * costs["decode_keyframe (message)"] + costs["decode_images (JPEG + depth)"]
    size_kb = statistics.mean(len(p) for p in payloads) / 1000
    body = "\n".join([
        "## Each keyframe decoded once on the server (issue 39)", "",
        f"`python bench/decode_once.py --frames {args.frames} --repeat {args.repeat}` at {git_rev()}; "
        f"{machine()}. {len(payloads)} keyframes (mean {size_kb:.0f} KB) of {args.scenario} seed {args.seed} "
        "through ingest's decode + insert, the back-end and the mapping stage (packaged segmenter, one "
        "thread each); CPU is the process's (all threads) from the first insert until the mapping stage "
        "is idle, per keyframe. A shared host: upper bounds, compare rows of one table.", "",
        "| mode | run | CPU ms / keyframe | wall ms / keyframe | cache hits | decoded from store | "
        "rasters decoded | evicted |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
        *rows, "",
        "| decode call, same keyframes | ms / keyframe |",
        "|---|---:|",
        *[f"| {k} | {v:.2f} |" for k, v in costs.items()], "",
        "Decoded once, the back-end and the mapping stage take ingest's message (no `decode_keyframe` "
        "of their own) and share one JPEG and depth decode, which the back-end does first: "
        f"{saved:.1f} ms per keyframe by the decode table (two `decode_keyframe`, one `decode_images`). "
        f"Median CPU per keyframe: {medians[MODES[0][0]]:.1f} ms each stage decoding, "
        f"{medians[MODES[1][0]]:.1f} ms decoded once; on a shared host single runs vary by more than that.",
    ])
    publish(body, args.write, "decode-once")


if __name__ == "__main__":
    main()
