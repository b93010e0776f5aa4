"""Bytes and encode/decode time of wire-schema v1 keyframes on simulated data (``wardmap.shared.wire``).

Renders ``walking_staff`` (seed 0) into a temporary folder, builds one keyframe per frame as a
robot sends it (JPEG q85 colour, 1000 ORB features, depth quantised to 1 mm, thermal to
0.01 K, intrinsics) and prints a markdown table: mean/max bytes per part and in total, and
mean encode/decode milliseconds (encode includes JPEG, depth and thermal compression; ORB
extraction is excluded). ``--depth-stride 2`` or ``4`` sends depth at reduced resolution.

    python bench/wire_size.py [--frames 20] [--depth-stride 1] [--no-thermal]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from wardmap.shared import wire
from wardmap.shared.dataset import DatasetReader, Frame
from wardmap.shared.se3 import se3_exp
from wardmap.sim.runner import generate


def _features(frame: Frame) -> wire.Keypoints:
    grey = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
    kps, desc = cv2.ORB.create(nfeatures=1000).detectAndCompute(grey, None)
    uv = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
    h, w = frame.depth_m.shape
    ij = np.clip(np.rint(uv).astype(int), 0, [w - 1, h - 1])
    return wire.Keypoints(
        uv, np.array([k.octave for k in kps], np.int8), np.array([k.angle for k in kps], np.float32),
        frame.depth_m[ij[:, 1], ij[:, 0]].astype(np.float32),
        desc if desc is not None else np.zeros((0, 32), np.uint8),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--depth-stride", type=int, default=1, choices=(1, 2, 4))
    ap.add_argument("--no-thermal", action="store_true")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    parts: dict[str, list[int]] = {"rgb": [], "depth": [], "thermal": [], "keypoints": [], "total": []}
    enc_ms: list[float] = []
    dec_ms: list[float] = []
    depth_ms: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        generate("walking_staff", 0, Path(tmp), frames=args.frames)
        reader = DatasetReader(tmp)
        for i in range(len(reader)):
            frame = reader.frame(i)
            keypoints = _features(frame)
            calib = reader.calibration
            s = args.depth_stride
            t0 = time.perf_counter()
            ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, 85])
            thermal = None
            if frame.thermal_k is not None and not args.no_thermal:
                thermal = wire.PackedRaster(*wire.encode_thermal(frame.thermal_k))
            msg = wire.KeyframeMsg(
                "robot_0", "bench", i, frame.stamp, se3_exp(rng.normal(size=6)), "rgb", keypoints,
                bytes(jpg.tobytes()), wire.PackedRaster(*wire.encode_depth(frame.depth_m[::s, ::s])),
                intrinsics=wire.Intrinsics.from_camera(calib.rgb, calib.depth_scale),
                T_odom_base=se3_exp(rng.normal(size=6)), thermal=thermal,
            )
            payload = wire.encode(msg)
            t1 = time.perf_counter()
            wire.encode_depth(frame.depth_m[::s, ::s])
            depth_ms.append((time.perf_counter() - t1) * 1e3)
            t1d = time.perf_counter()
            back = wire.decode_keyframe(payload)
            wire.decode_depth(back.depth.data, back.depth.meta)
            if back.thermal is not None:
                wire.decode_thermal(back.thermal.data, back.thermal.meta)
            t2 = time.perf_counter()
            if not ok:
                raise SystemExit("JPEG encoding failed")
            enc_ms.append((t1 - t0) * 1e3)
            dec_ms.append((t2 - t1d) * 1e3)
            parts["rgb"].append(len(msg.rgb_jpeg))
            parts["depth"].append(len(msg.depth.data))
            parts["thermal"].append(0 if msg.thermal is None else len(msg.thermal.data))
            parts["keypoints"].append(sum(getattr(keypoints, n).nbytes for n in
                                          ("uv", "octave", "angle_deg", "depth_m", "descriptors")))
            parts["total"].append(len(payload))
    n = len(parts["total"])
    print(f"wire v1 keyframes, walking_staff seed 0, {n} frames, depth stride {args.depth_stride}\n")
    print("| part | mean KB | max KB |")
    print("|---|---:|---:|")
    for name, sizes in parts.items():
        print(f"| {name} | {np.mean(sizes) / 1000:.1f} | {max(sizes) / 1000:.1f} |")
    print(f"\nencode (JPEG + depth + thermal + validate + msgpack): mean {np.mean(enc_ms):.1f} ms, "
          f"max {max(enc_ms):.1f} ms")
    print(f"decode (validate + depth/thermal decode): mean {np.mean(dec_ms):.1f} ms, "
          f"max {max(dec_ms):.1f} ms")
    print(f"encode_depth alone: mean {np.mean(depth_ms):.1f} ms, max {max(depth_ms):.1f} ms")


if __name__ == "__main__":
    main()
