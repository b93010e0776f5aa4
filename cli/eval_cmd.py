"""``wardmap eval``: score results against ground truth."""

from __future__ import annotations

import argparse
import json


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("eval", help="score a result against ground truth", description=__doc__)
    esub = p.add_subparsers(dest="eval_command", metavar="METRIC")
    esub.required = True
    a = esub.add_parser(
        "ate",
        help="absolute trajectory error of a TUM trajectory (evo)",
        description="Absolute trajectory error (translation RMSE, metres) of an estimated "
        "trajectory against a data set's groundtruth.txt or a TUM reference file.",
    )
    a.add_argument("estimate", metavar="TRAJ.txt", help="estimated trajectory (TUM format)")
    ref = a.add_mutually_exclusive_group(required=True)
    ref.add_argument("--dataset", metavar="DIR", help="data-set folder with groundtruth.txt")
    ref.add_argument("--reference", metavar="GT.txt", help="reference trajectory (TUM format)")
    a.add_argument("--align", choices=("se3", "sim3", "none"), default="se3", help="alignment (default se3)")
    a.add_argument("--max-diff", type=float, default=0.02, metavar="S", help="association window (s)")
    a.add_argument("--plot", metavar="FILE.png", help="also draw the trajectories and the error over time")
    a.set_defaults(func=run_ate)


def run_ate(args: argparse.Namespace) -> int:
    from wardmap.shared.dataset import DatasetReader, read_tum_trajectory
    from wardmap.shared.errors import DatasetError
    from wardmap.shared.metrics import ate_series

    est = read_tum_trajectory(args.estimate)
    if args.dataset:
        gt = DatasetReader(args.dataset).groundtruth()
        if gt is None:
            raise DatasetError(f"{args.dataset}: no groundtruth.txt")
    else:
        gt = read_tum_trajectory(args.reference)
    r, series = ate_series(est[0], est[1], gt[0], gt[1], align=args.align, max_diff_s=args.max_diff)
    if args.plot:
        from wardmap.tools.plots import plot_ate

        plot_ate(r, series, args.plot, title=f"{args.estimate}: ATE {r.rmse:.3f} m ({args.align} alignment)")
    print(
        json.dumps(
            {
                "ate_rmse_m": r.rmse,
                "mean_m": r.mean,
                "median_m": r.median,
                "max_m": r.max,
                "pairs": r.n,
                "align": args.align,
            }
        )
    )
    return 0
