"""Tracking frontend benchmark: ATE (evo, SE3 alignment), RPE and speed on every scenario.

Generates the simulator's scenarios (cached under --data) for each world seed, runs
``wardmap track``'s library function on each, and scores the trajectory against ground
truth (ATE; RPE: translation error per frame). Also runs the real TUM sample from ../shared
when present, out of the box (the readout model its folder gives) and as a global shutter.
With several seeds a second table gives each scenario's mean and worst over the seeds.
One core (numba/OpenCV threads = 1).

``--tum-subsequences`` tracks eleven sub-sequences of the TUM sample instead (starts 0, 5, ... 25
at every frame; every 2nd frame from 0 and 1; every 3rd from 0, 1 and 2: the camera turns two and
three times as far between frames) and reports each one's ATE, RPE, relocalisations and CPU time,
with the mean and the worst. ``--set KEY=VALUE`` overrides a ``[tracker]`` setting (TOML value),
e.g. ``--set sbi_scale=0`` for a before/after on the same tree.

Each sequence is tracked ``--repeats`` times (default 3): tracking is deterministic, so the
trajectory (and ATE) is the same every time, while a shared host's speed is not; the
ms/frame columns pool the per-frame times of all repeats, and each repeat's own median is
listed too.

    python bench/tracking.py [--data out/bench_data] [--seeds 2001 ...] [--repeats 3] [--write BENCHMARKS.md]
                             [--only NAME ...] [--detector ../shared/models/yolox_nano.onnx]
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import add_seed_arguments, git_rev, machine, tracker_config, write_section

from wardmap.edge.offline import track_source
from wardmap.edge.stream import FrameSourceStream
from wardmap.edge.tracker import TrackerConfig, TrackResult
from wardmap.shared.dataset import Calibration, DatasetReader
from wardmap.shared.metrics import ate, rpe
from wardmap.shared.se3 import transform_from_tum
from wardmap.sim.runner import generate
from wardmap.sim.scenarios import SCENARIOS, build_scene

ROOT = Path(__file__).resolve().parents[1]
TUM = ROOT.parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"
DETECTOR = ROOT.parent / "shared" / "models" / "yolox_nano.onnx"
SEG_MODEL = ROOT / "server" / "models" / "hospital_seg.onnx"
GOALS = {
    "aisle": "ATE <= 3 cm",
    "ward_chairs": "ATE <= 3 cm",
    "dark_corridor": "no lost frames, ATE <= 5 cm",
    "tum": "ATE <= 1.5 cm, RPE <= 0.9 cm/frame",
}


def read_tum(path: Path) -> tuple[list[float], list]:
    stamps, poses = [], []
    for line in path.read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        v = [float(x) for x in line.split()]
        stamps.append(v[0])
        poses.append(transform_from_tum(v[1:]))
    return stamps, poses


def run_one(folder: Path, labels: str, tmp: Path, calibration: Calibration | None = None,
            repeats: int = 1, config: TrackerConfig | None = None, associations: Path | None = None) -> dict:
    traj = tmp / f"{folder.name}_{labels.split(':')[0]}.txt"
    total: list[float] = []
    cpu: list[float] = []
    run_medians: list[float] = []
    thumbs = [0]  # frames tracked from the thumbnails' rotation (first run)
    for k in range(repeats):
        times: list[float] = []

        def keep(_i: int, _n: int, result: TrackResult, times: list[float] = times, k: int = k) -> None:
            times.append(result.timings_ms["total"])
            cpu.append(result.timings_ms["cpu_total"])
            thumbs[0] += int(k == 0 and result.source == "rgb" and "sbi" in result.timings_ms)

        out = traj if k == 0 else tmp / f"repeat_{traj.name}"
        summary = track_source(FrameSourceStream(DatasetReader(folder, associations=associations)), out,
                               labels=labels, calibration=calibration, progress=keep, config=config)
        if k == 0:
            first = summary
        elif out.read_text() != traj.read_text():
            raise SystemExit(f"{folder}: repeat {k + 1} gave another trajectory (not deterministic)")
        total += times
        run_medians.append(float(np.median(times)))
    gt = DatasetReader(folder).groundtruth()
    assert gt is not None
    st, T = read_tum(traj)
    res = ate(st, T, gt[0], gt[1])
    lab = first["labels_ms"]
    return {
        "ate_cm": 100 * res.rmse,
        "rpe_cm": 100 * rpe(st, T, gt[0], gt[1]).rmse,
        "readout": first["readout"],
        "frames": first["frames"],
        "lost": first["lost_frames"],
        "kf": first["keyframes"],
        "med": float(np.median(total)),
        "p95": float(np.percentile(total, 95)),
        "cpu": float(np.median(cpu)),
        "cpu_p95": float(np.percentile(cpu, 95)),
        "thumbs": thumbs[0],
        "runs": run_medians,
        "labels": "-" if lab is None else f"{lab['median']:.1f}",
        "sources": first["sources"],
        "ba": first["local_ba"],
    }


def _row(label: str, seed: str, kind: str, r: dict, ratio: str, goal: str) -> str:
    """One row of the per-sequence table."""
    ro = r["readout"]
    readout = f"{1e3 * ro['readout_s']:.1f} ms{' (guess)' if ro['assumed'] else ''}"
    src = ", ".join(f"{k} {v}" for k, v in sorted(r["sources"].items()))
    if r["thumbs"]:
        src += f" (rgb from thumbnails {r['thumbs']})"
    ba = r["ba"]
    if ba is not None:  # the bundle adjuster's CPU time per keyframe (inline: outside the frame's)
        src += (f"; BA {ba['solved']}/{ba['submitted']} solved, "
                f"{ba['cpu_ms_median']:.0f} ms ({ba['cpu_ms_p95']:.0f} p95)")
    runs = " / ".join(f"{m:.1f}" for m in r["runs"])
    return (
        f"| {label} | {seed} | {kind} | {readout} | {r['frames']} | {r['kf']} | {r['lost']} "
        f"| {r['ate_cm']:.2f} | {r['rpe_cm']:.2f} | {ratio} | {goal} | {r['med']:.1f} | {runs} "
        f"| {r['p95']:.1f} | {r['cpu']:.1f} | {r['labels']} | {src} |"
    )


SUBSEQUENCES = [*((k, 1) for k in (0, 5, 10, 15, 20, 25)), *((k, 2) for k in (0, 1)),
                *((k, 3) for k in (0, 1, 2))]
"""(first frame, stride) of the TUM sample's sub-sequences (``--tum-subsequences``)."""


def tum_subsequences(tmp: Path, config: TrackerConfig | None) -> str:
    """Markdown table: the TUM sample's sub-sequences (:data:`SUBSEQUENCES`) tracked out of the box."""
    text = (TUM / "associations.txt").read_text()
    lines = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
    rows, res = [], []
    for start, stride in SUBSEQUENCES:
        assoc = tmp / f"associations_{start}_{stride}.txt"
        assoc.write_text("\n".join(lines[start::stride]) + "\n")
        print(f"tracking the TUM sample from frame {start}, every {stride}", file=sys.stderr)
        r = run_one(TUM, "none", tmp, None, 1, config, associations=assoc)
        reloc = r["sources"].get("relocalised", 0)
        res.append((r["ate_cm"], r["rpe_cm"], reloc, r["lost"], r["thumbs"]))
        rows.append(f"| {start} | {stride} | {r['frames']} | {r['ate_cm']:.2f} | {r['rpe_cm']:.2f} | {reloc} "
                    f"| {r['thumbs']} | {r['lost']} | {r['cpu']:.1f} / {r['cpu_p95']:.1f} |")
        print(rows[-1])
    a = np.array(res)
    return "\n".join([
        "| first frame | every | frames | ATE RMSE cm | RPE cm/frame | relocalised | rgb from thumbnails "
        "| lost | CPU ms/frame median / p95 |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
        f"| **mean** | | | **{a[:, 0].mean():.2f}** | {a[:, 1].mean():.2f} | {a[:, 2].sum():.0f} (all) "
        f"| {a[:, 4].sum():.0f} (all) | {a[:, 3].sum():.0f} (all) | |",
        f"| **worst** | | | **{a[:, 0].max():.2f}** | {a[:, 1].max():.2f} | | | | |",
    ])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seed_arguments(ap, ROOT / "out" / "bench_data")
    ap.add_argument("--only", nargs="*", help="scenario names (default: all, plus tum)")
    ap.add_argument("--detector", type=Path, default=DETECTOR, help="YOLOX ONNX model for onnx labels")
    ap.add_argument("--seg-model", type=Path, default=SEG_MODEL, help="wardmap segmentation network "
                    "for onnx labels (default: the packaged one)")
    ap.add_argument("--no-generate", action="store_true",
                    help="skip (and list) scenarios without data under --data instead of rendering them")
    ap.add_argument("--repeats", type=int, default=3, help="times each sequence is tracked (default 3)")
    ap.add_argument("--local-ba", choices=["on", "off"], default=None,
                    help="local bundle adjustment on or off (default: the tracker's default)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a [tracker] setting, e.g. sbi_scale=0 (repeatable)")
    ap.add_argument("--tum-subsequences", action="store_true",
                    help="only the TUM sample's eleven sub-sequences (docstring), one table")
    ap.add_argument("--write", type=Path, help="update this markdown file's tracking section")
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    cv2.setNumThreads(1)
    local_ba = [] if args.local_ba is None else [f"local_ba.enabled = {str(args.local_ba == 'on').lower()}"]
    config = tracker_config(args.set + local_ba)
    if args.tum_subsequences:
        if not TUM.is_dir():
            raise SystemExit(f"no TUM sample at {TUM}")
        with tempfile.TemporaryDirectory() as tmpd:
            table = tum_subsequences(Path(tmpd), config)
        sets = "".join(f" --set {x}" for x in args.set)
        print(f"\nCommand: `python bench/tracking.py --tum-subsequences{sets}`  \n"
              f"Machine: {machine()}; one core; commit {git_rev()}.\n\n{table}")
        return 0
    names = args.only or [*SCENARIOS, "tum"]
    rows = []
    skipped: list[str] = []  # --no-generate: scenarios without data
    per_seed: dict[str, list[tuple[int, dict]]] = {}  # sequence label -> (seed, result) of each seed
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        for seed in args.seeds:
            for name in names:
                if name == "tum":
                    if seed != args.seeds[0]:
                        continue  # real data: one run, whatever the seeds
                    if not TUM.is_dir():
                        print(f"skip tum: {TUM} absent", file=sys.stderr)
                        continue
                    folders = [("tum_fr1_rpy_s3_first100", TUM)]
                else:
                    out = args.data / f"{name}_s{seed}"
                    runs = [p.parent for p in sorted(out.glob("*/sim.json"))]  # a multi-robot scenario
                    if not (out / "sim.json").exists() and len(runs) < len(build_scene(name, seed).robots):
                        if args.no_generate:
                            skipped.append(f"{name} seed {seed}")
                            continue
                        print(f"generating {name} seed {seed} ...", file=sys.stderr)
                        generate(name, seed, out, overwrite=True)
                        runs = [p.parent for p in sorted(out.glob("*/sim.json"))]
                    folders = [(f"{name}/{p.name}", p) for p in runs] if runs else [(name, out)]
                for label, folder in folders:
                    label_specs = ["none"]
                    if name == "walking_staff":
                        models = [m for m in (args.seg_model, args.detector) if m.is_file()]
                        label_specs += ["oracle"] + [f"onnx:{m}" for m in models]
                    runs: list[tuple[str, str, Calibration | None]] = [(label, s, None) for s in label_specs]
                    if name == "tum":
                        # Out of the box (the readout model the folder gives: the Kinect's default),
                        # and as a global shutter for comparison.
                        reader = DatasetReader(folder)
                        runs = [
                            (f"{label}, out of the box", "none", None),
                            (f"{label}, readout 0 (global shutter)", "none",
                             replace(reader.calibration, rgb_readout_s=0.0)),
                        ]
                    base = None
                    for label, spec, calib in runs:
                        print(f"tracking {label} seed {seed} labels={spec.split(':')[0]}", file=sys.stderr)
                        r = run_one(folder, spec, tmp, calib, args.repeats, config)
                        ratio = "" if base is None else f"{100 * r['ate_cm'] / base:.0f}% of none"
                        base = r["ate_cm"] if base is None else base
                        goal = next((g for k, g in GOALS.items() if label.startswith(k)), "")
                        if name == "walking_staff" and spec != "none":
                            goal = "<= 25% of none"
                        if name == "tum":
                            ratio = ""
                            goal = GOALS["tum"] if calib is None else ""
                        kind = spec if ":" not in spec else f"onnx {Path(spec.split(':', 1)[1]).stem}"
                        rows.append(_row(label, "-" if name == "tum" else str(seed), kind, r, ratio, goal))
                        print(rows[-1])
                        per_seed.setdefault(f"{label} | {kind}", []).append((seed, r))
    table = "\n".join(
        [
            "| sequence | seed | labels | readout | frames | keyframes | lost | ATE RMSE cm | RPE cm/frame "
            "| vs none | goal | ms/frame median | median of each run | ms/frame p95 | CPU ms/frame median "
            "| label ms median | pose sources |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
            *rows,
        ]
    )
    summary = [
        f"| {key} | {len(rs)} | {np.mean([r['ate_cm'] for _, r in rs]):.2f} "
        f"| {max(r['ate_cm'] for _, r in rs):.2f} (seed {max(rs, key=lambda x: x[1]['ate_cm'])[0]}) "
        f"| {np.mean([r['rpe_cm'] for _, r in rs]):.2f} | {max(r['rpe_cm'] for _, r in rs):.2f} "
        f"| {sum(r['ate_cm'] <= 1.5 for _, r in rs)}/{len(rs)} |"
        for key, rs in per_seed.items()
        if len(rs) > 1
    ]
    if summary:
        table += "\n\nOver the seeds:\n\n" + "\n".join(
            [
                "| sequence | labels | seeds | ATE mean cm | ATE worst cm | RPE mean cm/frame "
                "| RPE worst cm/frame | seeds with ATE <= 1.5 cm |",
                "|---|---|---|---|---|---|---|---|",
                *summary,
            ]
        )
    if skipped:
        table += "\n\nNot run (no data, --no-generate): " + ", ".join(skipped) + "."
    only = f" --only {' '.join(args.only)}" if args.only else ""
    body = (
        "## Tracking frontend (issues 3, 41)\n\n"
        f"Command: `python bench/tracking.py --seeds {' '.join(map(str, args.seeds))}{only}"
        f"{' --no-generate' if args.no_generate else ''}"
        f"{f' --local-ba {args.local_ba}' if args.local_ba else ''}"
        f"{''.join(f' --set {x}' for x in args.set)} "
        f"--repeats {args.repeats} --write BENCHMARKS.md`  \n"
        f"Machine: {machine()}; one core (numba/OpenCV threads = 1); commit {git_rev()}.\n"
        "ATE: evo, SE3 (Umeyama) alignment, translation RMSE. RPE: evo, translation error of each "
        "frame-to-frame step, RMSE. readout: the rolling-shutter readout time the recording's own "
        "calibration or sensor gives (no calibration command run first). ms/frame: the whole "
        "frontend, label inference excluded (its own column); wall clock, and the tracking thread's "
        "CPU time (`time.thread_time`), which time taken by other processes on a shared host does not "
        f"inflate. Each sequence was tracked {args.repeats} times (same trajectory each time); the "
        "medians and p95 pool the frames of all runs, and each run's own median is listed."
        "\n\n" + table
    )
    print(body)
    if args.write:
        write_section(args.write, "tracking", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
