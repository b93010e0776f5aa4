"""``wardmap train-seg``: train the hospital segmentation network and export it to ONNX."""

from __future__ import annotations

import argparse
import importlib.util
import json
import shlex
import sys
from typing import TYPE_CHECKING

from wardmap.cli.progress import Progress

if TYPE_CHECKING:
    from wardmap.tools.training.segdata import TrainSegConfig


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "train-seg",
        help="train the segmentation network on simulated frames, export ONNX + model card",
        description="Render training frames with the simulator (cached), train the BAFF segmentation "
        "network (paper 003) on the CPU, or on a GPU when torch sees one ([train_seg] device), export "
        "MODEL.onnx and write MODEL.md (model card) beside it. "
        "Needs the 'train' extra: pip install -e '.[train]'. The last line on stdout is a JSON summary.",
    )
    p.add_argument("--out", required=True, metavar="MODEL.onnx", help="ONNX file to write")
    p.add_argument(
        "--config", metavar="FILE", help="TOML file with a [train_seg] table (deploy/train_seg.toml)"
    )
    site = p.add_argument_group(
        "site images",
        "a site's own labelled images mixed with the simulated frames (override [train_seg.site]; "
        "docs/training.md, 'Fine-tuning on a site's images')",
    )
    site.add_argument("--site-coco", metavar="LABELS.json",
                      help="COCO-style instances file (polygons or RLE)")
    site.add_argument("--site-masks", metavar="DIR", help="CVAT 'Segmentation mask' export (labelmap.txt, "
                      "SegmentationClass/, JPEGImages/)")
    site.add_argument("--site-negatives", metavar="DIR",
                      help="images with no hospital object (all background)")
    site.add_argument("--init-weights", metavar="MODEL.onnx|MODEL.pt",
                      help="start from trained weights instead of random ones: an exported model of the same "
                      "config (e.g. server/models/hospital_seg.onnx) or the MODEL.pt of a run with "
                      "save_weights = true")
    p.add_argument(
        "--adjust",
        metavar="RAW.onnx",
        help="skip training: choose and bake the logit adjustment ([train_seg] logit_adjust) into RAW.onnx, "
        "a model from an earlier run without one, and write it to --out (needs onnx, not torch)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.shared.config import load_config
    from wardmap.tools.training.segdata import TrainingError, TrainSegConfig

    config = _with_site_arguments(load_config(TrainSegConfig, args.config, section="train_seg"), args)
    if args.adjust:
        return _adjust(args, config)
    from wardmap.tools.training.sitedata import check_site_paths

    check_site_paths(config.site)  # a mistyped site path fails now, not after the frames are rendered
    missing = [m for m in ("torch", "onnx") if importlib.util.find_spec(m) is None]
    if missing:
        raise TrainingError(
            f"{' and '.join(missing)} not installed; train-seg needs the train extra: "
            "pip install -e '.[train]'"
        )
    from wardmap.tools.training.training import train_and_export

    command = "wardmap " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    with Progress("steps") as bar:
        result = train_and_export(config, args.out, command=command, progress=bar.update)
    m = result.metrics
    print(
        json.dumps(
            {
                "onnx": str(result.onnx_path),
                "card": str(result.card_path),
                "val_miou": round(m["miou"], 2),
                "val_person_iou": m["per_class_iou"].get("person"),
                "val_frames": m["frames"],
                "ms_per_frame_1_thread": round(m["ms_per_frame"], 2),
                "wall_time_s": result.summary["wall_time_s"],
            }
        )
    )
    return 0


def _with_site_arguments(config: TrainSegConfig, args: argparse.Namespace) -> TrainSegConfig:
    """``config`` with the site options given on the command line."""
    from dataclasses import replace

    site = config.site
    options = (("site_coco", "coco_json"), ("site_masks", "mask_dir"), ("site_negatives", "negatives_dir"))
    for option, key in options:
        value = getattr(args, option)
        if value is not None:
            site = replace(site, **{key: value})
    config = replace(config, site=site)
    return replace(config, init_weights=args.init_weights) if args.init_weights is not None else config


def _adjust(args: argparse.Namespace, config: TrainSegConfig) -> int:
    from pathlib import Path

    from wardmap.shared.knowledge import KnowledgeGraph
    from wardmap.tools.training.logit_adjust import adjust_model
    from wardmap.tools.training.segdata import TrainingError, build_samples, class_weights

    if importlib.util.find_spec("onnx") is None:
        raise TrainingError("onnx not installed; --adjust needs it: pip install -e '.[train]'")
    src, dst = Path(args.adjust), Path(args.out)
    if not src.is_file():
        raise TrainingError(f"--adjust {src}: no such model file")
    if dst.suffix != ".onnx" or dst.is_dir():
        raise TrainingError(f"--out must be an .onnx file name, got {dst}")
    kg = KnowledgeGraph.load()
    print("loading training frames (class weights) and validation frames ...", file=sys.stderr)
    train = build_samples(config.data, config.cache_dir, kg=kg, workers=config.threads)
    val = build_samples(config.val, config.cache_dir, kg=kg, workers=config.threads)
    weights = class_weights(train.classes, len(val.names), config.class_weight_power, config.max_class_weight)
    done = adjust_model(src, dst, val, weights, config.logit_adjust, threads=config.threads)
    print(json.dumps({"onnx": str(dst), **done}))
    return 0
