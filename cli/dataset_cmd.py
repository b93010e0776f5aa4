"""``wardmap dataset info DIR``: validate a data-set folder and summarise it."""

from __future__ import annotations

import argparse
import json


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "dataset",
        help="inspect data-set folders",
        description="Inspect data-set folders (the TUM RGB-D layout and wardmap's extension).",
    )
    dsub = p.add_subparsers(dest="dataset_command", metavar="ACTION")
    dsub.required = True
    info = dsub.add_parser("info", help="check a data set and print a summary")
    info.add_argument("path", metavar="DIR", help="data-set folder (ours or a real TUM folder)")
    info.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    info.add_argument("--check-images", action="store_true", help="also decode every image")
    info.set_defaults(func=run_info)


def run_info(args: argparse.Namespace) -> int:
    from wardmap.shared.dataset import DatasetReader

    reader = DatasetReader(args.path)
    if args.check_images:
        for i in range(len(reader)):
            reader.frame(i)
    cam = reader.calibration.rgb
    gt = reader.groundtruth()
    odo = reader.odometry()
    objs = reader.objects()
    summary = {
        "path": str(reader.root),
        "frames": len(reader),
        "duration_s": round(float(reader.stamps[-1] - reader.stamps[0]), 3) if len(reader) else 0.0,
        "rgb_camera": (
            f"{cam.width}x{cam.height} fx={cam.fx:.1f} fy={cam.fy:.1f} cx={cam.cx:.1f} cy={cam.cy:.1f}"
        ),
        "thermal": reader.has_thermal,
        "labels": reader.has_labels,
        "groundtruth_poses": 0 if gt is None else len(gt[0]),
        "odometry_poses": 0 if odo is None else len(odo[0]),
        "objects": 0 if objs is None else len(objs.get("objects", [])),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        for k, v in summary.items():
            print(f"{k:<18} {v}")
    return 0
