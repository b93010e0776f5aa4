"""``wardmap map``: run perception + object association offline on data sets, write landmarks.json."""

from __future__ import annotations

import argparse
import json

from wardmap.cli.progress import Progress


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "map",
        help="associate object measurements of data sets into landmarks (paper 000), write landmarks.json",
        description="Select keyframes of each data set, measure its objects (oracle labels or a "
        "segmenter), associate them into object landmarks and write DIR/landmarks.json "
        "(docs/association.md). The last line on stdout is a JSON summary.",
    )
    p.add_argument("datasets", nargs="+", metavar="DATASET", help="data-set folder(s), one map in this order")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder for landmarks.json")
    p.add_argument(
        "--association",
        choices=("hierarchical", "per_keyframe_hdp", "nearest"),
        help="association method (default: the config's, hierarchical)",
    )
    p.add_argument(
        "--measurements",
        default="oracle",
        metavar="SPEC",
        help="instances from the simulator's labels (oracle, default) or a segmenter: model (the packaged "
        "network), model:PATH or PATH (an ONNX segmentation network), yolox:PATH (a COCO detector)",
    )
    p.add_argument(
        "--poses",
        action="append",
        metavar="TRAJ.txt",
        help="TUM trajectory T_world_camera instead of groundtruth.txt; once per data set, in order",
    )
    p.add_argument("--config", metavar="FILE", help="TOML with [association], [map], [measure] tables")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.tools.offline_map import run_map

    with Progress("keyframes") as bar:
        summary = run_map(
            args.datasets,
            args.out,
            method=args.association,
            measurements=args.measurements,
            poses=args.poses,
            config_path=args.config,
            progress=bar.update,
        )
    print(json.dumps(summary))
    return 0
