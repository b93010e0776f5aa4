"""ORB-SLAM3 RGB-D on frames read from stdin; run by bench/orbslam3.py in ITS OWN virtual
environment (pyorbslam3 is GPL: never imported by wardmap, never a wardmap dependency).

Imports only numpy and pyorbslam3. Protocol (little-endian, stdin):

- one JSON line: ``{"vocab", "settings", "trajectory", "frames", "height", "width"}``;
- then per frame: stamp (float64, seconds), RGB (height x width x 3 uint8, RGB order),
  depth (height x width float32, metres, 0 = none). All frames are read into memory first
  (a 575-frame simulated recording takes ~1.2 GB).

Each frame's ``track_rgbd`` call is timed: wall clock (``perf_counter``) and the calling
thread's CPU time (``thread_time``; ORB-SLAM3 tracks in the caller's thread, its local
mapping and loop closing run on threads of their own). After the last frame the system is
shut down and ORB-SLAM3 writes its own trajectory (``SaveTrajectoryTUM``: frames relative to
their optimised keyframes) to ``trajectory``. The last stdout line is JSON: the per-frame
times in ms, the tracking states, and the online poses (``T_world_camera`` as 16 row-major
floats, or null where ORB-SLAM3 gave none).
"""

from __future__ import annotations

import json
import struct
import sys
import time

import numpy as np
import pyorbslam3 as pos


def _read_exact(stream, n: int) -> bytes:  # type: ignore[no-untyped-def]
    data = stream.read(n)
    if len(data) != n:
        raise SystemExit(f"orbslam3 worker: input ended after {len(data)} of {n} bytes")
    return data


def main() -> int:
    stdin = sys.stdin.buffer
    head = json.loads(stdin.readline())
    h, w = int(head["height"]), int(head["width"])
    wall_ms, cpu_ms, states, poses, stamps = [], [], [], [], []
    # Every frame is read before the first is tracked, so reading and decoding never compete
    # with ORB-SLAM3 for the CPU while it is timed.
    frames = []
    for _ in range(int(head["frames"])):
        (stamp,) = struct.unpack("<d", _read_exact(stdin, 8))
        rgb = np.frombuffer(_read_exact(stdin, h * w * 3), np.uint8).reshape(h, w, 3)
        depth = np.frombuffer(_read_exact(stdin, h * w * 4), np.float32).reshape(h, w)
        frames.append((stamp, rgb, depth))
    slam = pos.Slam(head["vocab"], head["settings"], pos.Sensor.RGBD, use_viewer=False)
    try:
        for stamp, rgb, depth in frames:
            t0, c0 = time.perf_counter(), time.thread_time()
            result = slam.track_rgbd(rgb, depth, stamp)
            cpu_ms.append(1e3 * (time.thread_time() - c0))
            wall_ms.append(1e3 * (time.perf_counter() - t0))
            stamps.append(stamp)
            states.append(str(result.state).rsplit(".", 1)[-1])
            pose = result.pose_wc if result.pose_valid else None
            poses.append(None if pose is None else np.asarray(pose, np.float64).ravel().tolist())
    finally:
        slam.shutdown()
    slam.save_trajectory_tum(head["trajectory"])
    print(json.dumps({"stamps": stamps, "wall_ms": wall_ms, "cpu_ms": cpu_ms, "states": states,
                      "poses": poses}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
