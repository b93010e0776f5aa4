"""Simulator speed: frames per second for RGB-D + thermal + labels at full resolution.

Runs on one core (numba, OpenCV and BLAS threads pinned to 1). Measures the sensor
capture (render RGB 640x480 with depth and labels, render thermal 388x284, noise
models) and, separately, writing the frame's PNG files.

    python bench/sim_speed.py [--frames 100] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import git_rev, machine, write_section

from wardmap.shared.dataset import DatasetWriter
from wardmap.sim.geometry import TriangleSoup
from wardmap.sim.odometry import BaseGeometry
from wardmap.sim.runner import CAMERA_RATE_HZ, base_pose, calibration_of
from wardmap.sim.scenarios import build_scene
from wardmap.sim.sensors import SensorSimulator
from wardmap.sim.world import soup_of

SCENARIOS = ("aisle_slow_2", "walking_staff", "hospital_loop")


def measure(name: str, frames: int, tmp: Path) -> dict[str, float]:
    scene = build_scene(name, 0)
    run = scene.robots[0]
    sensors = SensorSimulator(scene.world.static, scene.world.bank.stack())
    n = min(frames, int(run.track.duration * CAMERA_RATE_HZ))
    t_cam = run.track.t[0] + np.arange(n) / CAMERA_RATE_HZ
    T_base = base_pose(run, t_cam)
    rng = np.random.default_rng(0)
    cap, wr = [], []
    with DatasetWriter(tmp / name, calibration_of(sensors.rig, BaseGeometry())) as writer:
        for i in range(n):
            t0 = time.perf_counter()
            t = float(t_cam[i])
            dyn = TriangleSoup.concat([soup_of(*a.at(t), a.id, scene.world.bank) for a in scene.actors])
            T = T_base[i] @ sensors.rig.T_base_rgb
            f = sensors.capture(T, dyn, scene.light(t), rng)
            t1 = time.perf_counter()
            writer.write_frame(
                1000.0 + t, f.rgb, f.depth_m, thermal_k=f.thermal_k, labels=f.labels, T_world_camera=T
            )
            t2 = time.perf_counter()
            if i >= 2:  # skip JIT warm-up frames
                cap.append(t1 - t0)
                wr.append(t2 - t1)
    c, w = np.array(cap) * 1e3, np.array(wr) * 1e3
    return {
        "frames": len(cap),
        "triangles": len(scene.world.static),
        "cap_med": float(np.median(c)),
        "cap_p95": float(np.percentile(c, 95)),
        "write_med": float(np.median(w)),
        "fps_render": 1e3 / float(np.median(c)),
        "fps_total": 1e3 / float(np.median(c + w)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100, help="frames per scenario (default 100)")
    ap.add_argument("--write", type=Path, help="update this markdown file's sim_speed section")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in SCENARIOS:
            r = measure(name, args.frames, Path(tmp))
            rows.append(
                f"| {name} | {r['triangles']} | {r['frames']} | {r['cap_med']:.1f} | {r['cap_p95']:.1f} "
                f"| {r['fps_render']:.1f} | {r['write_med']:.1f} | {r['fps_total']:.1f} |"
            )
    table = "\n".join(
        [
            "| scenario | static triangles | frames | capture ms (median) | capture ms (p95) "
            "| frames/s (capture) | PNG write ms (median) | frames/s (capture + write) |",
            "|---|---|---|---|---|---|---|---|",
            *rows,
        ]
    )
    body = (
        "## Simulator speed (issue 2: >= 10 frames/s, RGB-D + thermal + labels, one core)\n\n"
        f"Command: `python bench/sim_speed.py --frames {args.frames} --write BENCHMARKS.md`  \n"
        f"Machine: {machine()}; numba/OpenCV threads = 1; commit {git_rev()}.\n"
        "Capture = render RGB 640x480 + depth + labels, render thermal 388x284, sensor noise.\n\n" + table
    )
    print(body)
    if args.write:
        write_section(args.write, "sim_speed", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
