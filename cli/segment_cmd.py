"""``wardmap segment``: per-pixel classes of every frame of a data set, for scoring."""

from __future__ import annotations

import argparse
import json

from wardmap.cli.progress import Progress


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "segment",
        help="segment every frame of a data set into class-index PNGs",
        description="Run a segmenter on every frame of a data-set folder and write DIR/<stamp>.png "
        "(uint8 class index per pixel) and DIR/classes.json (index -> class name). The last line "
        "on stdout is a JSON summary. See docs/perception.md.",
    )
    p.add_argument("dataset", metavar="DATASET", help="data-set folder")
    p.add_argument(
        "--model",
        metavar="SPEC",
        help="model | model:PATH | yolox:PATH | PATH (= model:PATH); default: [perception] "
        "segmenter of --config, else the packaged model",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (must be empty)")
    p.add_argument("--config", metavar="FILE", help="TOML file with a [perception] table")
    p.add_argument("--threads", type=int, metavar="N", help="CPU threads of the network")
    p.add_argument("--max-frames", type=int, metavar="K", help="segment only the first K frames")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.server.perception.config import load_perception_config
    from wardmap.server.perception.segment import segment_dataset

    config = load_perception_config(args.config)
    with Progress("frames") as bar:
        summary = segment_dataset(
            args.dataset,
            args.out,
            args.model or config.segmenter,
            config=config,
            threads=args.threads,
            max_frames=args.max_frames,
            overwrite=args.overwrite,
            progress=lambda i, n: bar.update("segment", i, n),
        )
    print(json.dumps(summary))
    return 0
