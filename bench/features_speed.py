"""Speed of the tracking frontend's building blocks on one core (``wardmap.edge.features`` / ``pose``).

Times, as the median over repeated calls after a warm-up (numba JIT or cache load):

- grid ORB extraction (1000 features, 8x6 grid, 8 levels) on 640x480 grey frames: the
  real TUM fr1 frames in ``../shared/data/tum_fr1_rpy_s3_first100`` when present, else
  a synthetic textured image;
- guided matching of 1500 projected map points against the frame's features;
- EPnP + RANSAC and the Huber motion-only refinement on 300 synthetic correspondences
  (30 % outliers, TUM fr1 distortion);
- adaptive SIFT on a 388x284 thermal-like frame (for reference; not in the RGB budget).

    python bench/features_speed.py [--repeats 30] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import functools
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import git_rev, machine, write_section

from wardmap.edge.features import (
    OrbExtractor,
    SiftConfig,
    extract_sift_adaptive,
    match_projected,
)
from wardmap.edge.pose import refine_pose_huber, solve_pnp_ransac
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import inverse, se3_exp, transform_points

TUM_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"
TUM_FR1 = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))


def _synthetic_frame(seed: int, h: int = 480, w: int = 640, n: int = 1500) -> NDArray[np.uint8]:
    """Grey frame of random filled rectangles and circles (seeded)."""
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 0.15, np.float32)
    for _ in range(n):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        val = float(rng.uniform(0.15, 0.85))
        if rng.random() < 0.5:
            cv2.circle(img, c, int(rng.integers(2, 30)), val, -1)
        else:
            s = rng.integers(3, 60, size=2)
            cv2.rectangle(img, c, (c[0] + int(s[0]), c[1] + int(s[1])), val, -1)
    return (img * 255).astype(np.uint8)


def _frames(limit: int) -> tuple[str, list[NDArray[np.uint8]]]:
    files = sorted((TUM_DIR / "rgb").glob("*.png")) if TUM_DIR.is_dir() else []
    if files:
        frames = [np.asarray(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), np.uint8) for f in files[:limit]]
        return f"TUM fr1_rpy, {len(frames)} real frames", frames
    return "synthetic textured frames", [_synthetic_frame(s) for s in range(5)]


def _median_ms(fn: Callable[[], Any], repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def _time_over_frames(fn: Callable[[NDArray[np.uint8]], Any], frames: list[NDArray[np.uint8]]) -> float:
    """Median ms of ``fn(frame)`` over all frames, each timed once after one warm-up call."""
    fn(frames[0])
    times = []
    for f in frames:
        t0 = time.perf_counter()
        fn(f)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def _pnp_scene(seed: int) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    rng = np.random.default_rng(seed)
    T = se3_exp([0.3, -0.2, 0.5, 0.1, -0.2, 0.15])
    n = 300
    uv_true = np.column_stack([rng.uniform(15, 625, n), rng.uniform(15, 465, n)])
    P = transform_points(inverse(T), TUM_FR1.unproject(uv_true, rng.uniform(1, 6, n)))
    uv = uv_true + rng.normal(0, 1, (n, 2))
    out = rng.random(n) < 0.3
    uv[out] = np.column_stack([rng.uniform(0, 640, out.sum()), rng.uniform(0, 480, out.sum())])
    return P, uv, T


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--frames", type=int, default=100, help="real frames to time ORB on")
    ap.add_argument("--write", type=Path, help="update this markdown file's features_speed section")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    source, frames = _frames(args.frames)
    extractor = OrbExtractor()
    counts = [len(extractor.extract(f)) for f in frames]
    orb_ms = _time_over_frames(extractor.extract, frames)
    orb_once_ms = _median_ms(lambda: extractor.extract(frames[0]), args.repeats)

    # Guided matching: 1500 map points, the frame's features re-observed with noise.
    rng = np.random.default_rng(0)
    feats = extractor.extract(frames[0])
    n = len(feats)
    map_desc = np.concatenate([feats.descriptors, rng.integers(0, 256, (1500 - n, 32), dtype=np.uint8)])
    map_uv = np.concatenate(
        [feats.uv + rng.normal(0, 1.5, (n, 2)), rng.uniform((0, 0), (640, 480), (1500 - n, 2))]
    )
    match_ms = _median_ms(lambda: match_projected(map_desc, map_uv, feats, radius_px=15.0), args.repeats)
    n_matched = match_projected(map_desc, map_uv, feats, radius_px=15.0)[0].size

    P, uv, _ = _pnp_scene(0)
    pnp = solve_pnp_ransac(P, uv, TUM_FR1)
    pnp_ms = _median_ms(lambda: solve_pnp_ransac(P, uv, TUM_FR1), args.repeats)
    refine_ms = _median_ms(lambda: refine_pose_huber(P, uv, TUM_FR1, pnp.T_cam_world), args.repeats)

    # Thermal-sized frames: a textured one (one detection at the initial threshold) and a
    # washed-out one (the loop runs down to min_contrast: the worst case).
    sift_rows = []
    small = np.asarray(cv2.resize(frames[0], (388, 284), interpolation=cv2.INTER_AREA), np.float32)
    textured = np.asarray(cv2.resize(_synthetic_frame(1), (388, 284), interpolation=cv2.INTER_AREA), np.uint8)
    for label, frame in (("textured", textured), ("washed-out", (60 + 0.1 * small).astype(np.uint8))):
        sift_feats, contrast = extract_sift_adaptive(frame, SiftConfig())
        sift_ms = _median_ms(
            functools.partial(extract_sift_adaptive, frame, SiftConfig()), max(3, args.repeats // 5), 1
        )
        sift_rows.append(
            (
                f"adaptive SIFT, 388x284 {label} frame",
                sift_ms,
                f"{len(sift_feats)} features at contrast {contrast:.3f}",
            )
        )

    rows = [
        (
            f"ORB grid extraction, 640x480 ({source}, median over frames)",
            orb_ms,
            f"{int(np.median(counts))} features (min {min(counts)})",
        ),
        ("ORB grid extraction, one frame repeated", orb_once_ms, f"{counts[0]} features"),
        ("guided matching, 1500 map points x frame features", match_ms, f"{n_matched} matches of {n}"),
        ("EPnP + RANSAC, 300 points, 30 % outliers", pnp_ms, "ok" if pnp.ok else pnp.reason),
        ("Huber refinement (4 rounds x <= 10 LM), 300 points", refine_ms, ""),
        *sift_rows,
    ]
    lines = ["| step | median ms | note |", "| --- | ---: | --- |"]
    lines += [f"| {name} | {ms:.2f} | {note} |" for name, ms, note in rows]
    table = "\n".join(lines)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"one core; load average {load:.1f} while measuring (other processes slow the timings)\n")
    print(table)
    body = (
        "## Tracking building blocks (one core)\n\n"
        f"Command: `python bench/features_speed.py --repeats {args.repeats} --write BENCHMARKS.md`  \n"
        f"Machine: {machine()}; OpenCV/numba threads = 1; load average {load:.1f}; "
        f"commit {git_rev()}.\n\n{table}\n"
    )
    if args.write:
        write_section(args.write, "features_speed", body)


if __name__ == "__main__":
    main()
