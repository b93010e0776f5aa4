"""``wardmap track``: run the edge tracking frontend offline on a data-set folder."""

from __future__ import annotations

import argparse
import json
import sys
import time


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "track",
        help="run the tracking frontend on a data set, write a TUM trajectory",
        description="Track every frame of a data-set folder (ours or a real TUM folder) and write "
        "the camera trajectory in TUM format. The last line on stdout is a JSON summary.",
    )
    p.add_argument("dataset", metavar="DATASET", help="data-set folder")
    p.add_argument("--out", required=True, metavar="TRAJ.txt", help="trajectory file to write")
    p.add_argument("--config", metavar="FILE", help="TOML file with a [tracker] table")
    p.add_argument(
        "--labels",
        default="none",
        metavar="SOURCE",
        help="label source for dynamic-point removal: none | oracle | onnx:PATH (default none)",
    )
    p.add_argument("--label-threads", type=int, default=1, metavar="N", help="threads for label inference")
    p.add_argument("--max-frames", type=int, metavar="K", help="stop after K frames")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.edge.offline import track_dataset
    from wardmap.edge.tracker import TrackerConfig
    from wardmap.shared.config import load_config

    config = load_config(TrackerConfig, args.config, section="tracker")
    last = [time.monotonic()]

    def progress(i: int, n: int, res: object) -> None:
        now = time.monotonic()
        if i == n or now - last[0] > 2.0:
            last[0] = now
            print(f"\rframe {i}/{n}", end="\n" if i == n else "", file=sys.stderr, flush=True)

    summary = track_dataset(
        args.dataset,
        args.out,
        config=config,
        labels=args.labels,
        max_frames=args.max_frames,
        label_threads=args.label_threads,
        progress=progress,
    )
    print(json.dumps(summary))
    return 0
