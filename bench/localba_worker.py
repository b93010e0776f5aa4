"""Local bundle adjustment in its worker process, frames fed at the recording's own rate.

What the edge daemon does (``[tracker.local_ba] worker = "process"``), without the transport:
frames of a data-set folder are tracked no faster than their stamps, the adjustments solved
in one worker process and applied at frame boundaries. Reports the tracking thread's CPU
time per frame (``time.thread_time``; the worker's time is not in it), the worker's CPU time
per keyframe, how many problems were solved or superseded (a newer keyframe came while one
waited), the largest backlog (solving + waiting, bounded at 2) and ATE / RPE. The trajectory
depends on when solutions arrive, so it is not reproducible run to run (``wardmap track``
solves inline for that).

    python bench/localba_worker.py DATASET [DATASET ...] [--speed 1.0]
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from wardmap.edge.localba import LocalBaConfig
from wardmap.edge.tracker import Tracker, TrackerConfig, TrackInput
from wardmap.shared.dataset import DatasetReader, odom_at
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.metrics import ate, rpe


def run(folder: Path, speed: float) -> dict:
    reader = DatasetReader(folder)
    odo = reader.odometry()
    config = TrackerConfig(local_ba=LocalBaConfig(enabled=True, worker="process"))
    stamps, poses, cpu = [], [], []
    with Tracker(reader.calibration, config, KnowledgeGraph.load().mobility_lut()) as tracker:
        t_wall0, stamp0 = time.monotonic(), None
        for i in range(len(reader)):
            f = reader.frame(i)
            stamp0 = f.stamp if stamp0 is None else stamp0
            lag = (f.stamp - stamp0) / speed - (time.monotonic() - t_wall0)
            if lag > 0:
                time.sleep(lag)  # no faster than the recording
            res = tracker.track(TrackInput(f.stamp, f.rgb, f.depth_m, f.thermal_k, odom_at(odo, f.stamp)))
            stamps.append(res.stamp)
            poses.append(res.T_world_camera)
            cpu.append(res.timings_ms["cpu_total"])
        ba = tracker.local_ba_stats()
    gt = reader.groundtruth()
    assert gt is not None
    return {
        "sequence": folder.name, "frames": len(stamps),
        "ate_cm": round(100 * ate(stamps, poses, gt[0], gt[1]).rmse, 2),
        "rpe_cm": round(100 * rpe(stamps, poses, gt[0], gt[1]).rmse, 2),
        "tracking_cpu_ms_median": round(float(np.median(cpu)), 1), "local_ba": ba,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("datasets", nargs="+", type=Path)
    ap.add_argument("--speed", type=float, default=1.0, help="times the recording's rate (default 1)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    for folder in args.datasets:
        print(json.dumps(run(folder, args.speed)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
