"""``wardmap track``: run the edge tracking frontend offline on a data-set folder."""

from __future__ import annotations

import argparse
import json
import sys

from wardmap.cli.progress import Progress
from wardmap.cli.sources import SOURCE_HELP, SOURCE_METAVAR, add_source_options, open_source, readout_line


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "track",
        help="run the tracking frontend on a data set, write a TUM trajectory",
        description="Track every frame of a data-set folder (ours or a real TUM folder), a ROS "
        "recording (bag:PATH) or a simulated robot (sim:SCENARIO) and write the camera trajectory in "
        "TUM format. Says on stderr which rolling-shutter readout time it uses and why. The last line on "
        "stdout is a JSON summary.",
    )
    p.add_argument("dataset", nargs="?", metavar="DATASET", help="data-set folder (or use --source)")
    p.add_argument("--source", metavar=SOURCE_METAVAR, help=SOURCE_HELP)
    p.add_argument("--out", required=True, metavar="TRAJ.txt", help="trajectory file to write")
    p.add_argument("--config", metavar="FILE", help="TOML file with [tracker] and [source] tables")
    p.add_argument(
        "--labels",
        default="none",
        metavar="SOURCE",
        help="label source for dynamic-point removal: none | oracle | onnx:PATH (default none)",
    )
    p.add_argument("--label-threads", type=int, default=1, metavar="N", help="threads for label inference")
    p.add_argument("--max-frames", type=int, metavar="K", help="stop after K frames")
    add_source_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.edge.offline import track_source
    from wardmap.edge.tracker import TrackerConfig
    from wardmap.shared.config import load_config
    from wardmap.shared.errors import ConfigError

    if (args.dataset is None) == (args.source is None):
        raise ConfigError("give the data set as DATASET or --source (one of them)")
    config = load_config(TrackerConfig, args.config, section="tracker")
    source = open_source(args.dataset or args.source, args, args.config)
    readout = readout_line(source.calibration)
    with Progress("frames") as bar:
        summary = track_source(
            source,
            args.out,
            config=config,
            labels=args.labels,
            max_frames=args.max_frames,
            label_threads=args.label_threads,
            progress=lambda i, n, _result: _progress(bar, readout, i, n),
        )
    print(json.dumps(summary))
    return 0


def _progress(bar: Progress, readout: str, i: int, n: int) -> None:
    if i == 1:  # once tracking runs: a command that fails before says one line only
        print(readout, file=sys.stderr, flush=True)
    bar.update("track", i, n)
