"""``wardmap vocab train``: train an ORB vocabulary (DBoW2 text format, as ORB-SLAM loads)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from wardmap.cli.progress import Progress


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("vocab", help="train an ORB bag-of-words vocabulary",
                       description="ORB vocabularies (hierarchical k-medians, DBoW2 text format; "
                       "docs/tracking.md, 'Reference: ORB-SLAM3').")
    actions = p.add_subparsers(dest="action", metavar="ACTION")
    actions.required = True
    train = actions.add_parser(
        "train", help="train a vocabulary on the frames of data-set folders",
        description="Extract the tracker's ORB features from every --every-th frame of each data-set "
        "folder, cluster them into a k-ary tree of --depth levels (k-medians, Hamming distance) and "
        "write it in the DBoW2 text format ORB-SLAM2/3 load. Train on recordings you may use: "
        "training on a recording you then evaluate on is a leak. Progress on stderr, JSON last on stdout.",
    )
    train.add_argument("datasets", nargs="+", metavar="DATASET", help="data-set folders (ours or TUM)")
    train.add_argument("--out", required=True, metavar="FILE", help="vocabulary file to write")
    train.add_argument("--k", type=int, default=10, help="branching factor, 2-20 (default 10)")
    train.add_argument("--depth", type=int, default=6, metavar="L",
                       help="levels, 1-10 (default 6: ORB-SLAM matches within the nodes 4 levels up)")
    train.add_argument("--every", type=int, default=5, metavar="N", help="use every N-th frame (default 5)")
    train.add_argument("--seed", type=int, default=0, help="k-means++ seed (default 0)")
    train.add_argument("--force", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from wardmap.shared.errors import WardmapError
    from wardmap.tools.vocabulary import MAX_DEPTH, MAX_K, dataset_descriptors, train_vocabulary

    if not 2 <= args.k <= MAX_K:
        raise WardmapError(f"--k must be 2-{MAX_K} (ORB-SLAM's loader limit), got {args.k}")
    if not 1 <= args.depth <= MAX_DEPTH:
        raise WardmapError(f"--depth must be 1-{MAX_DEPTH}, got {args.depth}")
    if args.every < 1:
        raise WardmapError(f"--every must be at least 1, got {args.every}")
    out = Path(args.out)
    if out.is_dir():
        raise WardmapError(f"--out {out} is a folder; give the vocabulary file's name")
    if not out.parent.is_dir():
        raise WardmapError(f"--out: folder {out.parent} does not exist")
    if out.exists() and not args.force:
        raise WardmapError(f"--out {out} exists; add --force to replace it")
    for d in args.datasets:
        if not Path(d).is_dir():
            raise WardmapError(f"{d}: not a data-set folder")
    with Progress("frames") as bar:
        images = dataset_descriptors(args.datasets, every=args.every,
                                     progress=lambda f, i, n: bar.update(f, i, n))
    with Progress("levels") as bar:
        voc = train_vocabulary(images, k=args.k, depth=args.depth, seed=args.seed,
                               progress=lambda i, n: bar.update("k-medians", i, n))
    voc.save(out)
    print(f"wrote {out}: {voc.words.shape[0]} words", file=sys.stderr)
    print(json.dumps({
        "out": str(out), "k": args.k, "depth": args.depth, "images": len(images),
        "descriptors": int(sum(d.shape[0] for d in images)), "words": int(voc.words.shape[0]),
        "nodes": int(voc.parents.shape[0]), "mean_idf": round(float(np.mean(voc.weights[voc.words])), 4),
    }))
    return 0
