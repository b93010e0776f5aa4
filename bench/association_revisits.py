"""Association cost when a robot drives the same route again and again.

A hospital robot passes the same objects many times a day, so each landmark keeps gaining
measurements. This feeds one data set's keyframes (oracle or model measurements, ground-truth
poses) to one :class:`Associator` ``--passes`` times, each pass a new robot session, and
prints per pass: milliseconds per keyframe, landmarks, the most measurements one landmark has
had, the measurements the associator holds in memory (as on the server:
``keep_measurements`` off), and the size of its pickled state with the time to write and read
it (the mapping stage's association checkpoint, server/pipeline.py). The landmark count should
stay at the first pass's, and time and memory should level off once landmarks have
``AssociationConfig.max_history`` measurements.

    python bench/association_revisits.py [--data out/bench_data] [--sequence aisle_slow_2]
        [--seed 1001] [--passes 8] [--measurements oracle|model] [--max-history N [N ...]]
        [--write BENCHMARKS.md]

Several ``--max-history`` values give one column group each (a huge value stands for no bound).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import pickle
import sys
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import git_rev, machine, publish

from wardmap.server.association.associator import AssociationConfig, Associator
from wardmap.server.mapping import for_association
from wardmap.sim.runner import generate
from wardmap.tools.offline_map import measure_dataset

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT / "out" / "bench_data")
    ap.add_argument("--sequence", default="aisle_slow_2")
    ap.add_argument("--seed", type=int, default=1001)
    ap.add_argument("--passes", type=int, default=8)
    ap.add_argument("--measurements", choices=("oracle", "model"), default="model")
    ap.add_argument("--max-history", type=int, nargs="+", default=[AssociationConfig().max_history],
                    help="AssociationConfig.max_history values to compare (default: the default)")
    ap.add_argument("--write", type=Path, help="update this markdown file's association_revisits section")
    args = ap.parse_args()
    if args.passes < 1:
        raise SystemExit("--passes must be >= 1")
    cv2.setNumThreads(1)
    folder = args.data / f"{args.sequence}_s{args.seed}"
    if not (folder / "sim.json").exists():
        print(f"generating {folder.name} ...", file=sys.stderr)
        generate(args.sequence, args.seed, folder, overwrite=True)
    ds = measure_dataset(folder, measurements=args.measurements)
    keyframes = [(for_association(kf.measurements), kf.T_world_camera) for kf in ds.keyframes]
    results: dict[int, list[tuple[float, int, int, int, float, float, float]]] = {}
    for history in args.max_history:
        assoc = Associator(AssociationConfig(max_history=history, keep_measurements=False))
        results[history] = []
        for p in range(args.passes):
            t0 = time.perf_counter()
            for measurements, T in keyframes:
                assoc.add_keyframe(measurements, T, ds.camera, stream=f"robot/pass{p}")
            assoc.flush(f"robot/pass{p}")
            ms = 1e3 * (time.perf_counter() - t0) / len(keyframes)
            lms = assoc.landmarks()
            most = max((lm.n_measurements for lm in lms), default=0)
            held = sum(len(lm.measurements) for lm in lms)
            t0 = time.perf_counter()
            state = pickle.dumps(assoc, protocol=pickle.HIGHEST_PROTOCOL)
            t1 = time.perf_counter()
            pickle.loads(state)
            t2 = time.perf_counter()
            results[history].append((ms, len(lms), most, held, len(state) / 1e6, 1e3 * (t1 - t0),
                                     1e3 * (t2 - t1)))
            print(f"max_history {history}, pass {p + 1}: {ms:.1f} ms/keyframe, {len(lms)} landmarks, "
                  f"at most {most} measurements, {held} held, state {len(state) / 1e6:.2f} MB",
                  file=sys.stderr)
    heads = " | ".join(f"ms/keyframe, landmarks, measurements held; state MB, write / read ms "
                       f"(max_history {h})" for h in args.max_history)
    lines = [
        "## Association on a route driven again and again (issue 6)\n",
        f"Command: `python bench/association_revisits.py --sequence {args.sequence} --seed {args.seed} "
        f"--passes {args.passes} --measurements {args.measurements} --max-history "
        + " ".join(str(h) for h in args.max_history) + " --write BENCHMARKS.md`  ",
        f"Machine: {machine()}; commit {git_rev()}. {len(keyframes)} keyframes per pass, each pass a new "
        "session of one robot; time = association only (hierarchical), one thread.",
        "",
        f"| pass | most measurements on one landmark | {heads} |",
        "|---|---|" + "---|" * len(args.max_history),
    ]
    for p in range(args.passes):
        cells = " | ".join(f"{r[0]:.1f}, {r[1]}, {r[3]}; {r[4]:.2f}, {r[5]:.0f} / {r[6]:.0f}"
                           for r in (results[h][p] for h in args.max_history))
        lines.append(f"| {p + 1} | {results[args.max_history[0]][p][2]} | {cells} |")
    text = "\n".join(lines)
    publish(text, args.write, "association_revisits")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
