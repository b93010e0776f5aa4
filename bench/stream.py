"""Streaming source benchmark: a recording replayed on a camera clock into the tracker, one core.

Writes each input as an MCAP recording (``wardmap dataset to-bag``'s library function), then
replays it through ``FrameStream`` at the camera rate with ``drop_when_behind`` (policy
drop-oldest, the slot of the edge's default ``stream_capacity``) into the tracker, as ``wardmap
edge --source bag:PATH --rate HZ --drop-when-behind`` does, and counts frames received, tracked
and dropped. Latency is stream release (the frame's time on the replay clock) -> its pose from
the tracker, with labels ``none``. A throwaway tracker first tracks a few frames untimed (numba
compiles its kernels on first use). Inputs: the TUM
excerpt from ../shared (640x480, 30 Hz) when present, and a simulated aisle (10 Hz).

    python bench/stream.py [--data out/bench_data] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import argparse
import os
import tempfile
import time

import _one_core  # noqa: F401  (one thread per library, before numba and OpenCV load)
import cv2
import numpy as np
from _report import git_rev, machine, publish

from wardmap.edge.agent import AgentConfig
from wardmap.edge.bag import BagSource
from wardmap.edge.stream import FrameStream
from wardmap.edge.tracker import Tracker, TrackInput
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.sim.runner import generate
from wardmap.tools.bags import dataset_to_bag

ROOT = Path(__file__).resolve().parents[1]
TUM = ROOT.parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"
WARM_UP_FRAMES = 5
"""Frames tracked by a throwaway tracker first (numba compiles on first use)."""


def replay(bag: Path, rate_hz: float, drop: bool) -> dict[str, float]:
    """Replay ``bag`` at ``rate_hz`` (0: as fast as possible) into a tracker, dropping frames when
    behind if ``drop``; counts, tracking ms and latency ms."""
    source = BagSource(bag)
    lut = KnowledgeGraph.load().mobility_lut()
    warm = Tracker(source.calibration, None, lut)  # compiles the numba kernels before the clock runs
    with FrameStream(source, max_frames=WARM_UP_FRAMES) as stream:
        for item in stream:
            if item.frame is not None:
                warm.track(TrackInput(item.stamp, item.frame.rgb, item.frame.depth_m, None, item.T_odom_base))
    tracker = Tracker(source.calibration, None, lut)
    track_ms: list[float] = []
    latency_ms: list[float] = []
    with FrameStream(source, capacity=AgentConfig().stream_capacity, rate_hz=rate_hz,
                     drop_when_behind=drop) as stream:
        for item in stream:
            t0 = time.monotonic()
            f = item.frame
            if f is None:
                tracker.track(TrackInput(item.stamp, None, None, item.T_odom_base, problem=item.problem))
            else:
                tracker.track(TrackInput(item.stamp, f.rgb, f.depth_m, f.thermal_k, item.T_odom_base))
            t1 = time.monotonic()
            track_ms.append((t1 - t0) * 1e3)
            latency_ms.append((t1 - item.released_s) * 1e3)
    c = stream.counters()
    return {"received": c["received"], "tracked": len(track_ms), "dropped": c["dropped"], "late": c["late"],
            "track_p50": float(np.median(track_ms)), "track_p95": float(np.percentile(track_ms, 95)),
            "lat_p50": float(np.median(latency_ms)),
            "lat_p95": float(np.percentile(latency_ms, 95))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT / "out" / "bench_data")
    ap.add_argument("--write", type=Path, help="put the table into this BENCHMARKS.md")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    inputs: list[tuple[str, Path, float, str]] = []
    if TUM.is_dir():
        inputs.append(("TUM fr1/rpy excerpt", TUM, 30.0, "640x480"))
    aisle = args.data / "stream_aisle_slow_1_s0"
    if not (aisle / "rgb.txt").is_file():
        generate("aisle_slow_1", 0, aisle, frames=100, overwrite=True)
    inputs.append(("simulated aisle_slow_1", aisle, 10.0, "simulated rig"))
    rows = []
    load = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        for name, folder, hz, size in inputs:
            bag = Path(tmp) / f"{folder.name}.mcap"
            dataset_to_bag(folder, bag)
            for rate, drop, how in ((hz, True, f"{hz:.0f} Hz camera clock, drop-oldest"),
                                    (0.0, False, "as fast as possible, block")):
                r = replay(bag, rate, drop)
                rows.append(
                    f"| {name} ({size}) | {how} | {r['received']:.0f} | {r['tracked']:.0f} | "
                    f"{r['dropped']:.0f} ({100 * r['dropped'] / r['received']:.0f} %) | {r['late']:.0f} | "
                    f"{r['track_p50']:.1f} / {r['track_p95']:.1f} | "
                    f"{r['lat_p50']:.1f} / {r['lat_p95']:.1f} |")
    body = "\n".join([
        "## Streaming sources: a recording on a camera clock (issue 38)",
        "",
        f"`python bench/stream.py --write BENCHMARKS.md` at {git_rev()}; {machine()}; load average",
        f"{load[0]:.1f} / {load[1]:.1f} (1 / 5 min) when it started (a shared host: figures are upper",
        "bounds); one core for the tracker (numba/OpenCV threads = 1), the replay on its own thread. Each",
        "input is written as an MCAP",
        "recording and replayed through the edge's stream (slot of 2) into the tracker, labels `none`:",
        "at the camera rate, dropping the oldest frame when the tracker is behind (`--rate HZ",
        "--drop-when-behind`), and as fast as the tracker goes (nothing dropped). Latency: stream release",
        "-> tracked pose, ms (as fast as possible, it includes the wait in the slot).",
        "A dropped frame widens the motion to the next one, so the tracker relocalises more and slows down.",
        "",
        "| input | replay | received | tracked | dropped | late | track ms p50 / p95 "
        "| latency ms p50 / p95 |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
    ])
    publish(body, args.write, "stream")
    return 0


if __name__ == "__main__":
    sys.exit(main())
