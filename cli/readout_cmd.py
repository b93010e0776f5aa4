"""``wardmap calibrate-readout``: estimate the colour camera's rolling-shutter readout time."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from wardmap.cli.progress import Progress


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "calibrate-readout",
        help="estimate the colour camera's rolling-shutter readout time from a recording",
        description="Track the first frames of a data-set folder once per candidate readout time and "
        "keep the one under which the most keypoints fit a rigid pose (no ground truth needed; the "
        "recording should turn the camera). Shows progress on stderr and prints a JSON summary on stdout; "
        "--write saves a calibration.toml with [rgb] readout_s set (docs/tracking.md).",
    )
    p.add_argument("dataset", metavar="DATASET", help="data-set folder (ours or a real TUM folder)")
    p.add_argument("--config", metavar="FILE", help="TOML file with a [tracker] table")
    p.add_argument("--max-frames", type=int, default=300, metavar="N", help="frames to track (default 300)")
    p.add_argument("--max-ms", type=float, default=40.0, metavar="MS", help="largest candidate (default 40)")
    p.add_argument("--step-ms", type=float, default=2.5, metavar="MS", help="candidate spacing (default 2.5)")
    p.add_argument("--write", metavar="FILE", help="save the calibration with the estimate to FILE")
    p.add_argument("--force", action="store_true", help="let --write replace an existing file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    import numpy as np

    from wardmap.edge.readout import estimate_readout
    from wardmap.edge.tracker import TrackerConfig
    from wardmap.shared.config import load_config
    from wardmap.shared.dataset import MAX_READOUT_S, DatasetReader, save_calibration
    from wardmap.shared.errors import WardmapError

    if not (0 < args.step_ms <= args.max_ms <= 1e3 * MAX_READOUT_S):
        raise WardmapError(
            f"need 0 < --step-ms <= --max-ms <= {1e3 * MAX_READOUT_S:g}, "
            f"got {args.step_ms:g} and {args.max_ms:g}"
        )
    if args.max_frames < 10:
        raise WardmapError(f"--max-frames must be at least 10, got {args.max_frames}")
    out = Path(args.write) if args.write else None
    if out is not None:
        if out.is_dir():
            raise WardmapError(f"--write {out} is a folder; give the calibration file's name")
        if not out.parent.is_dir():
            raise WardmapError(f"--write: folder {out.parent} does not exist")
        if out.exists() and not args.force:
            raise WardmapError(
                f"--write {out} exists; add --force to replace it (its values are kept, comments are not)"
            )
    config = load_config(TrackerConfig, args.config, section="tracker")
    reader = DatasetReader(args.dataset)
    cands = [round(float(c), 6) for c in np.arange(0.0, args.max_ms + 1e-9, args.step_ms) / 1e3]

    with Progress("candidates") as bar:
        done = 0

        def progress(c: float, inl: float) -> None:
            nonlocal done
            done += 1
            bar.update("readout", done, len(cands), note=f"{1e3 * c:.1f} ms: {inl:.1f} inliers per frame")

        est = estimate_readout(reader, config, candidates_s=cands, max_frames=args.max_frames,
                               progress=progress)
    if est.decisive:
        print(f"estimated readout time: {1e3 * est.readout_s:.1f} ms", file=sys.stderr)
    else:
        print(
            f"no readout time stands out (best {100 * est.gain:+.1f} % inliers over 0 ms, 3 % needed): "
            "0 (global shutter); record the camera turning to estimate it",
            file=sys.stderr,
        )
    if out is not None:
        save_calibration(out, replace(reader.calibration, rgb_readout_s=est.readout_s))
        print(f"wrote {out}", file=sys.stderr)
    summary = {
        "readout_s": est.readout_s,
        "decisive": est.decisive,
        "gain": round(est.gain, 4),
        "frames": est.frames,
        "candidates_s": list(est.candidates_s),
        "inliers_per_frame": [round(x, 2) for x in est.inliers_per_frame],
        "written": str(out) if out is not None else None,
    }
    print(json.dumps(summary))
    return 0
