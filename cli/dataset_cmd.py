"""``wardmap dataset info|from-bag|to-bag``: inspect data-set folders, convert ROS recordings."""

from __future__ import annotations

import argparse
import json

from wardmap.cli.progress import Progress
from wardmap.cli.sources import add_associations_option, add_bag_options, bag_config


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
    add_associations_option(info)
    info.set_defaults(func=run_info)

    fb = dsub.add_parser("from-bag", help="convert a ROS 1/ROS 2/MCAP recording to a data-set folder",
                         description="Read colour, registered depth, CameraInfo, tf and odometry from a "
                         "recording (topics by the options or the config's [source] table) and write "
                         "our data-set layout (docs/dataset.md).")
    fb.add_argument("bag", metavar="BAG", help="a ROS 1 .bag, a ROS 2 bag folder or an .mcap file")
    fb.add_argument("--out", required=True, metavar="DIR", help="data-set folder to write")
    fb.add_argument("--config", metavar="FILE", help="TOML file with a [source] table")
    fb.add_argument("--overwrite", action="store_true", help="replace the data-set files in DIR")
    add_bag_options(fb)
    fb.set_defaults(func=run_from_bag)

    tb = dsub.add_parser("to-bag", help="write a data-set folder as a ROS recording",
                         description="Write a data set's colour, depth, CameraInfo, odometry and camera "
                         "mount (/tf_static) as a recording --source bag:PATH reads without options: "
                         "OUT ending in .bag is a ROS 1 bag, in .mcap one MCAP file, else a ROS 2 bag "
                         "folder. Thermal images, labels and ground truth are not written.")
    tb.add_argument("path", metavar="DIR", help="data-set folder")
    tb.add_argument("--out", required=True, metavar="BAG", help="recording to write")
    tb.add_argument("--rgb", choices=("raw", "png", "jpeg"), default="raw",
                    help="colour as a raw rgb8 Image or a PNG/JPEG CompressedImage (default raw)")
    tb.add_argument("--depth", choices=("32FC1", "16UC1"), default="32FC1",
                    help="depth as 32FC1 metres (lossless) or 16UC1 millimetres (default 32FC1)")
    tb.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3",
                    help="storage of a ROS 2 bag folder (default sqlite3)")
    tb.add_argument("--max-frames", type=int, metavar="K", help="write the first K frames only")
    tb.add_argument("--overwrite", action="store_true", help="replace BAG if it exists")
    tb.set_defaults(func=run_to_bag)


def run_info(args: argparse.Namespace) -> int:
    from wardmap.shared.dataset import DatasetReader

    reader = DatasetReader(args.path, associations=args.associations)
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
        "associations": str(reader.associations) if reader.associations else "nearest stamps",
        "rgb_readout_s": reader.calibration.readout.readout_s,
        "rgb_readout_source": reader.calibration.readout.source,
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


def run_from_bag(args: argparse.Namespace) -> int:
    from wardmap.tools.bags import bag_to_dataset

    with Progress("frames") as bar:
        summary = bag_to_dataset(args.bag, args.out, config=bag_config(args, args.config),
                                 overwrite=args.overwrite, progress=lambda i, n: bar.update("from-bag", i, n))
    print(json.dumps(summary))
    return 0


def run_to_bag(args: argparse.Namespace) -> int:
    from wardmap.tools.bags import dataset_to_bag

    with Progress("frames") as bar:
        summary = dataset_to_bag(args.path, args.out, rgb_format=args.rgb, depth_encoding=args.depth,
                                 storage=args.storage, max_frames=args.max_frames, overwrite=args.overwrite,
                                 progress=lambda i, n: bar.update("to-bag", i, n))
    print(json.dumps(summary))
    return 0
