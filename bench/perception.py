"""Server perception benchmark (issue 5): measurement accuracy, segmentation quality, speed.

1. Oracle instances (the simulator's instance labels) -> 3D measurements on simulated
   worlds never used in training or tuning (seeds 2001-2005 by default), scored against ``objects.json``:
   median centroid error and median yaw error of static objects (goal <= 10 cm, 10 deg).
2. The trained network (``server/models/hospital_seg.onnx`` or ``--model PATH``), when
   present: mIoU over all classes and per class against the simulator labels, person
   IoU, inference ms per keyframe on one thread, and measurement accuracy with the
   network's own instances.
3. The real TUM sequence ``../shared/data/tum_fr1_rpy_s3_first100`` with the YOLOX adapter:
   world-frame centroids (ground-truth camera poses) of the monitor measured from keyframes
   every 10 frames; spread = largest distance to their median (goal <= 10 cm).

Yaw of a measured box is only defined modulo 180 deg (and x is its longer horizontal
side, docs/perception.md), so the yaw error compares the measured x axis with the ground
truth's longer horizontal axis modulo 180 deg, and modulo 90 deg for near-square
footprints (sides within 10 %), where "longer" is arbitrary.

Seeds (``--seeds``, default 2001-2005): every figure is given per seed, with the mean and the
worst seed, so a setting tuned on one world cannot carry the table. Seed ranges: training
worlds < 1000, the training validation split 1000, tuning 1001-1002, evaluation 2001-2005
(``bench/_report.py``).

    python bench/perception.py [--data out/bench_data] [--seeds 2001 ... 2005] [--frames 300]
        [--every 10] [--model PATH] [--yolox PATH] [--jobs N] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import multiprocessing
import sys
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import EVAL_SEEDS, TUNE_SEEDS, add_seed_arguments, git_rev, machine, publish

from wardmap.server.perception.config import PerceptionConfig, measure_config_for
from wardmap.server.perception.floor import floor_under
from wardmap.server.perception.instances import id_to_class, oracle_instances
from wardmap.server.perception.keyframe import ORACLE, measure_keyframe
from wardmap.server.perception.measure import MeasureConfig, measure_instances
from wardmap.server.perception.models import OnnxSegmenter, make_segmenter, packaged_model_path
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.dataset import DatasetReader, Frame
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.sim.runner import generate
from wardmap.tools.training.segdata import EVAL_SEED_MIN

ROOT = Path(__file__).resolve().parents[1]
TUM = ROOT.parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"
YOLOX = ROOT.parent / "shared" / "models" / "yolox_nano.onnx"
SCENES = ("aisle_slow_1", "ward_chairs", "hospital_loop", "walking_staff")
CLUSTER_M = 0.5
"""TUM: monitor measurements closer than this belong to one physical monitor."""
SQUARE_RATIO = 0.9
"""A footprint whose shorter side is at least this fraction of the longer is near-square."""


# ---------------------------------------------------------------------------- ground truth


@dataclass
class Truth:
    """Ground truth of one simulated data set."""

    classes: dict[int, str]
    mobility: dict[int, str]
    size: dict[int, np.ndarray]
    pose: dict[int, np.ndarray]
    trajectory: dict[int, dict[float, np.ndarray]] = field(default_factory=dict)
    moved: set[int] = field(default_factory=set)

    @staticmethod
    def load(reader: DatasetReader) -> Truth:
        doc = reader.objects()
        if doc is None:
            raise SystemExit(f"{reader.root}: no objects.json")
        t = Truth(id_to_class(doc), {}, {}, {})
        for o in doc["objects"]:
            k = int(o["id"])
            t.mobility[k] = str(o["mobility"])
            t.size[k] = np.asarray(o["size"], float)
            t.pose[k] = np.asarray(o["T_world_object"], float)
            if o.get("trajectory"):
                t.trajectory[k] = {round(float(p["stamp"]), 6): np.asarray(p["T_world_object"], float)
                                   for p in o["trajectory"]}
                first = next(iter(t.trajectory[k].values()))
                if any(np.linalg.norm(T[:3, 3] - first[:3, 3]) > 0.01 for T in t.trajectory[k].values()):
                    t.moved.add(k)
        return t

    def pose_at(self, k: int, stamp: float) -> np.ndarray:
        traj = self.trajectory.get(k)
        if traj is None:
            return self.pose[k]
        return traj.get(round(stamp, 6), self.pose[k])


def yaw_error_deg(m: ObjectMeasurement, T_gt: np.ndarray, size_gt: np.ndarray) -> float:
    """Angle between the measured x axis and the ground truth's longer horizontal axis (module doc)."""
    axis = 0 if size_gt[0] >= size_gt[1] else 1
    gt = T_gt[:3, axis]
    meas = m.T_world_object[:3, 0]
    period = math.pi / 2 if min(size_gt[:2]) >= SQUARE_RATIO * max(size_gt[:2]) else math.pi
    d = (math.atan2(meas[1], meas[0]) - math.atan2(gt[1], gt[0])) % period
    return math.degrees(min(d, period - d))


@dataclass
class Scores:
    """Errors of measurements against ground truth, by group."""

    centroid_m: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    yaw_deg: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    unmatched: int = 0
    skipped: int = 0

    def add(self, m: ObjectMeasurement, truth: Truth, width: int, height: int) -> None:
        k = m.gt_instance
        if k is None or k not in truth.classes:
            self.unmatched += 1
            return
        if truth.mobility[k] == "static":
            group = "static"
        elif truth.mobility[k] == "movable" and k not in truth.moved:
            group = "movable (not moved)"
        else:
            return
        T_gt = truth.pose_at(k, m.stamp)
        err = float(np.linalg.norm(m.T_world_object[:3, 3] - T_gt[:3, 3]))
        yaw = yaw_error_deg(m, T_gt, truth.size[k])
        x1, y1, x2, y2 = m.box_xyxy
        inside = x1 > 0 and y1 > 0 and x2 < width and y2 < height
        for g in (group, f"{group}, not cut by the image border" if inside else None,
                  f"class {truth.classes[k]}"):
            if g is not None:
                self.centroid_m[g].append(err)
                self.yaw_deg[g].append(yaw)

    def rows(self, source: str) -> list[str]:
        out = []
        for g in sorted(self.centroid_m, key=lambda s: (s.startswith("class"), s)):
            c, y = np.asarray(self.centroid_m[g]), np.asarray(self.yaw_deg[g])
            goal = "<= 10 cm, <= 10 deg" if g == "static" else ""
            out.append(f"| {source} | {g} | {c.size} | {100 * np.median(c):.1f} "
                       f"| {100 * np.percentile(c, 90):.1f} "
                       f"| {np.median(y):.1f} | {np.percentile(y, 90):.1f} | {goal} |")
        return out


# ---------------------------------------------------------------------------- simulated data


def dataset(data: Path, scene: str, seed: int, frames: int) -> DatasetReader:
    out = data / f"{scene}_s{seed}_f{frames}"
    if not (out / "sim.json").exists() and not (out / "robot_0" / "sim.json").exists():
        print(f"generating {scene} seed {seed} ({frames} frames) ...", file=sys.stderr)
        generate(scene, seed, out, frames=frames, overwrite=True)
    return DatasetReader(out if (out / "sim.json").exists() else out / "robot_0")


def bgr_of(frame: Frame) -> np.ndarray:
    return np.ascontiguousarray(frame.rgb[..., ::-1])


def class_image(labels: np.ndarray, truth: Truth, names: tuple[str, ...]) -> np.ndarray:
    """Knowledge-graph class index per pixel from the instance-id label image."""
    lut = np.zeros(int(labels.max()) + 1, np.uint8)
    for k, c in truth.classes.items():
        if k < lut.size:
            lut[k] = names.index(c)
    return lut[labels]


# ---------------------------------------------------------------------------- TUM


def tum_monitor(yolox: Path) -> list[str]:
    """Markdown lines: the monitor's world centroids from TUM keyframes, for each measure config."""
    reader = DatasetReader(TUM)
    seg = make_segmenter(f"yolox:{yolox}", threads=1)
    seen, times = [], []
    for i in range(0, len(reader), 10):
        frame = reader.frame(i)
        if frame.T_world_camera is None:
            continue
        out = seg.segment(bgr_of(frame), frame.depth_m)
        times.append(out.inference_ms)
        seen.append((i, frame, [m for m in out.instances if m.category == "wall_monitor"]))
    lines = [
        "### Real data: TUM fr1/rpy excerpt, YOLOX-Nano adapter, the monitor\n",
        f"Keyframes every 10 frames of `tum_fr1_rpy_s3_first100` ({len(seen)} keyframes), world frame = "
        f"ground-truth poses; YOLOX + masks median {np.median(times):.0f} ms per keyframe, one thread. "
        f"Measurements within {CLUSTER_M} m of each other are one physical monitor; the spread (largest "
        "distance to the median centroid) is given for the monitor measured most often. The screen "
        "itself returns no depth (Kinect on a black screen): \"depth %\" is the share of mask pixels "
        "with depth.\n",
    ]
    yolox_default = measure_config_for(PerceptionConfig(), f"yolox:{YOLOX}")
    for label, cfg in ((f"server default for `yolox:` (largest 3D piece, `cluster_gap_m = "
                        f"{yolox_default.cluster_gap_m}`)", yolox_default),
                       ("no clustering (`cluster_gap_m = 0`, the network's default)", MeasureConfig())):
        centroids = []
        for i, frame, monitors in seen:
            for m in measure_instances(monitors, bgr=bgr_of(frame), depth_m=frame.depth_m,
                                       camera=reader.calibration.rgb, T_world_camera=frame.T_world_camera,
                                       keyframe=f"tum/{i}", stamp=frame.stamp, config=cfg):
                valid = float(np.mean(frame.depth_m[m.mask] > 0))
                centroids.append((i, m.confidence, m.T_world_object[:3, 3], m.size, valid))
        if not centroids:
            lines.append(f"{label}: no monitor measured.\n")
            continue
        pts = np.array([c[2] for c in centroids])
        cluster = np.arange(len(pts))  # single linkage within CLUSTER_M
        for a in range(len(pts)):
            for b in range(len(pts)):
                if np.linalg.norm(pts[a] - pts[b]) < CLUSTER_M:
                    cluster[cluster == cluster[b]] = cluster[a]
        main = cluster == int(np.bincount(cluster).argmax())
        dist = np.linalg.norm(pts - np.median(pts[main], axis=0), axis=1)
        lines += [
            f"**{label}**: {len(centroids)} monitor measurements, {int(main.sum())} on the main monitor; "
            f"spread **{100 * dist[main].max():.1f} cm**, median distance "
            f"{100 * np.median(dist[main]):.1f} cm (goal <= 10 cm).\n",
            "| frame | score | depth % | centroid world m | size m | object | distance to main median cm |",
            "|---|---|---|---|---|---|---|",
        ]
        for (i, conf, p, size, valid), d, own in zip(centroids, dist, main, strict=True):
            lines.append(f"| {i} | {conf:.2f} | {100 * valid:.0f} | {p[0]:.3f} {p[1]:.3f} {p[2]:.3f} "
                         f"| {size[0]:.2f} {size[1]:.2f} {size[2]:.2f} | {'main' if own else 'other'} "
                         f"| {100 * d:.1f} |")
        lines.append("")
    return lines


# ---------------------------------------------------------------------------- one seed


@dataclass
class SeedRun:
    """What one world seed gave: measurement scores and, with a network, its confusion matrix."""

    seed: int
    keyframes: int = 0
    oracle: Scores = field(default_factory=Scores)
    learned: Scores = field(default_factory=Scores)
    confusion: np.ndarray | None = None
    net_ms: list[float] = field(default_factory=list)
    seg_ms: list[float] = field(default_factory=list)
    measure_ms: list[float] = field(default_factory=list)
    floating: int = 0
    walls: int = 0
    floors: int = 0

    def iou(self) -> np.ndarray:
        """Per-class IoU (C,), NaN where a class is neither in the truth nor predicted."""
        assert self.confusion is not None
        cm = self.confusion
        inter = np.diag(cm).astype(float)
        union = cm.sum(0) + cm.sum(1) - np.diag(cm)
        return np.where(union > 0, inter / np.maximum(union, 1), np.nan)


def run_seed(seed: int, args: argparse.Namespace, model_path: Path) -> SeedRun:
    """Measure every keyframe of ``args.scenes`` at world ``seed`` with the oracle and, when
    ``model_path`` exists, the network. Runs in a worker process with ``--jobs``."""
    cv2.setNumThreads(1)
    kg = KnowledgeGraph.load()
    names = ("background", *kg.names)
    model_spec = f"model:{model_path}"
    model: OnnxSegmenter | None = None
    if model_path.is_file():
        seg = make_segmenter(model_spec, threads=1)
        assert isinstance(seg, OnnxSegmenter)
        model = seg
    perception = PerceptionConfig()
    moving = kg.moving_classes()
    run = SeedRun(seed, confusion=None if model is None else np.zeros((len(names), len(names)), np.int64))
    for scene in args.scenes:
        reader = dataset(args.data, scene, seed, args.frames)
        truth = Truth.load(reader)
        cam = reader.calibration.rgb
        T_base_rgb = reader.calibration.T_base_rgb
        for i in range(0, len(reader), args.every):
            frame = reader.frame(i)
            if frame.labels is None or frame.T_world_camera is None:
                continue
            run.keyframes += 1
            key = f"{reader.root.name}/{frame.stamp:.6f}"
            started = time.perf_counter()
            # The server's perception steps (keyframe.measure_keyframe): people left out, the
            # ground truth neither split nor checked against the floor.
            seen = measure_keyframe(bgr_of(frame), frame.depth_m, cam, frame.T_world_camera, keyframe=key,
                                    stamp=frame.stamp, floor_z_m=None,
                                    instances=oracle_instances(frame.labels, truth.classes),
                                    config=perception, moving=moving, source=ORACLE)
            run.measure_ms.append((time.perf_counter() - started) * 1e3)
            run.oracle.skipped += len(seen.skipped)
            for m in seen.measurements:
                run.oracle.add(m, truth, cam.width, cam.height)
            if model is None or run.confusion is None:
                continue
            started = time.perf_counter()
            classes, _ = model.classify(bgr_of(frame), frame.depth_m)
            run.net_ms.append((time.perf_counter() - started) * 1e3)
            out = model.segment(bgr_of(frame), frame.depth_m)
            run.seg_ms.append(out.inference_ms)
            gt = class_image(frame.labels, truth, names)
            run.confusion += np.bincount(gt.ravel().astype(np.int64) * len(names) + classes.ravel(),
                                         minlength=len(names) ** 2).reshape(len(names), len(names))
            # As the server does (keyframe.measure_keyframe): touching chairs in one mask cut
            # apart, people left out, misplaced instances left out where the floor is known.
            floor = None if T_base_rgb is None else floor_under(frame.T_world_camera, T_base_rgb)
            seen = measure_keyframe(bgr_of(frame), frame.depth_m, cam, frame.T_world_camera, keyframe=key,
                                    stamp=frame.stamp, floor_z_m=floor, instances=out.instances,
                                    config=perception, moving=moving, source=model_spec,
                                    instance_ids=frame.labels)
            run.floating += seen.left_out.floating
            run.walls += seen.left_out.walls
            run.floors += seen.left_out.floors
            run.learned.skipped += len(seen.skipped)
            for m in seen.measurements:
                run.learned.add(m, truth, cam.width, cam.height)
        print(f"seed {seed} {scene}: done", file=sys.stderr)
    return run


def merged(scores: list[Scores]) -> Scores:
    """One :class:`Scores` holding every entry of ``scores``."""
    out = Scores()
    for s in scores:
        for g, v in s.centroid_m.items():
            out.centroid_m[g] += v
        for g, v in s.yaw_deg.items():
            out.yaw_deg[g] += v
        out.unmatched += s.unmatched
        out.skipped += s.skipped
    return out


def network_section(runs: list[SeedRun], names: tuple[str, ...], model_path: Path, size: tuple[int, int]
                    ) -> list[str]:
    """Markdown: per seed mIoU, person IoU, per-class IoU and network time; mean and worst."""
    ious = np.array([r.iou() for r in runs])  # (seeds, C)
    miou = np.nanmean(ious, axis=1)
    person = ious[:, names.index("person")]
    net = np.array([np.median(r.net_ms) for r in runs])
    present = ~np.all(np.isnan(ious), axis=0)
    cols = [c for c in range(len(names)) if present[c]]
    truth_px = np.array([r.confusion.sum(1) for r in runs if r.confusion is not None])  # (seeds, C)
    head = ("| seed | mIoU % | person IoU % | network ms (median) | "
            + " | ".join(names[c] for c in cols) + " |")
    lines = [
        f"### Trained network ({model_path.name}, input {size[0]}x{size[1]})\n",
        "mIoU over the classes present in the truth or the prediction of each seed (background included; "
        "a class painted where the seed has none counts as 0). Per class IoU %; \"-\": neither in the "
        "truth nor predicted; \"(0 px)\": predicted but absent from the truth. Network time per keyframe: "
        "resize, onnxruntime, argmax, softmax, one thread.\n",
        head,
        "|" + "---|" * (4 + len(cols)),
    ]

    def cell(k: int, c: int) -> str:
        v = ious[k, c]
        if np.isnan(v):
            return "-"
        return f"{100 * v:.1f}" + (" (0 px)" if truth_px[k, c] == 0 else "")

    for k, r in enumerate(runs):
        lines.append(f"| {r.seed} | {100 * miou[k]:.1f} | {100 * person[k]:.1f} | {net[k]:.1f} | "
                     + " | ".join(cell(k, c) for c in cols) + " |")
    mean_c = np.nanmean(ious[:, cols], axis=0)
    worst_c = np.nanmin(ious[:, cols], axis=0)
    lines.append(f"| **mean** | **{100 * miou.mean():.1f}** | {100 * person.mean():.1f} | {net.mean():.1f} | "
                 + " | ".join(f"{100 * v:.1f}" for v in mean_c) + " |")
    lines.append(f"| **worst** | **{100 * miou.min():.1f}** | {100 * person.min():.1f} | {net.max():.1f} | "
                 + " | ".join(f"{100 * v:.1f}" for v in worst_c) + " |")
    zero = [f"{names[c]} (seed {r.seed}, {truth_px[k, c]:,} px)" for k, r in enumerate(runs) for c in cols
            if truth_px[k, c] >= 1000 and ious[k, c] == 0]
    all_net = np.concatenate([r.net_ms for r in runs])
    all_seg = np.concatenate([r.seg_ms for r in runs])
    lines += [
        "",
        f"Mean mIoU **{100 * miou.mean():.1f} %**, worst seed **{100 * miou.min():.1f} %** (issue 42 goals: "
        f">= 80 % and >= 75 %); person IoU mean {100 * person.mean():.1f} %, "
        f"worst {100 * person.min():.1f} % "
        f"(goal >= 90 %). Classes at 0 where the truth has >= 1,000 pixels: {', '.join(zero) or 'none'}.  ",
        f"Network time per keyframe over all seeds: median **{np.median(all_net):.1f} ms**, p95 "
        f"{np.percentile(all_net, 95):.1f} ms; with instance extraction: median {np.median(all_seg):.1f} ms, "
        f"p95 {np.percentile(all_seg, 95):.1f} ms.\n",
    ]
    return lines


# ---------------------------------------------------------------------------- main


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seed_arguments(ap, ROOT / "out" / "bench_data")
    ap.add_argument("--frames", type=int, default=300, help="frames generated per scenario")
    ap.add_argument("--every", type=int, default=10, help="keyframe every N frames")
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--model", type=Path, help="segmentation network (default: the packaged one)")
    ap.add_argument("--yolox", type=Path, default=YOLOX)
    ap.add_argument("--jobs", type=int, default=1, help="seeds measured in parallel (processes)")
    ap.add_argument("--write", type=Path, help="update this markdown file's perception section")
    args = ap.parse_args()
    if any(s < EVAL_SEED_MIN for s in args.seeds):
        print(f"warning: seeds < {EVAL_SEED_MIN} are training worlds", file=sys.stderr)
    if args.jobs < 1:
        ap.error("--jobs must be >= 1")
    kg = KnowledgeGraph.load()
    names = ("background", *kg.names)
    model_path = args.model or packaged_model_path()
    if args.model is not None and not args.model.is_file():
        ap.error(f"--model {args.model}: no such file")
    if args.jobs > 1 and len(args.seeds) > 1:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(min(args.jobs, len(args.seeds)), mp_context=ctx) as pool:
            n = len(args.seeds)
            runs = list(pool.map(run_seed, args.seeds, [args] * n, [model_path] * n))
    else:
        runs = [run_seed(seed, args, model_path) for seed in args.seeds]
    oracle = merged([r.oracle for r in runs])
    learned = merged([r.learned for r in runs])
    keyframes = sum(r.keyframes for r in runs)
    seeds = " ".join(map(str, args.seeds))
    header = ("| instances | objects | measurements | centroid median cm | centroid p90 cm | yaw median deg "
              "| yaw p90 deg | goal |\n|---|---|---|---|---|---|---|---|")
    kind = ("evaluation worlds: never used in training or tuning" if set(args.seeds) <= set(EVAL_SEEDS)
            else "not all of them evaluation worlds")
    parts = [
        "## Server perception (issue 5)\n",
        f"Command: `python bench/perception.py --seeds {seeds} --frames {args.frames} --every {args.every}"
        f"{' --model ' + str(args.model) if args.model else ''} --write BENCHMARKS.md`  \n"
        f"Machine: {machine()}; one thread per seed; commit {git_rev()}.  \n"
        f"Simulated data: {', '.join(args.scenes)}, seeds {seeds} ({kind}), first "
        f"{args.frames} frames, a keyframe every {args.every} frames: {keyframes} keyframes. People are "
        "not measured (moving). Yaw error modulo 180 deg (90 deg for near-square footprints), see the "
        "script's docstring. Seed ranges: training < 1000, training validation 1000, tuning "
        f"{', '.join(map(str, TUNE_SEEDS))}, evaluation {EVAL_SEEDS[0]}-{EVAL_SEEDS[-1]}.\n",
        "### 3D measurements against objects.json (all seeds)\n",
        header,
        *oracle.rows("oracle"),
        f"\nOracle: {oracle.skipped} instance(s) of >= 200 pixels skipped for too few depth points (the "
        "simulated sensor returns no depth beyond its range, so far objects have none); measurement "
        "time median "
        f"{np.median(np.concatenate([r.measure_ms for r in runs])):.0f} ms per keyframe (all instances of "
        "the keyframe).\n",
    ]
    if any(r.confusion is None for r in runs):
        parts.append(f"### Trained network\n\nNo segmentation model at {model_path}: mIoU, person IoU, "
                     "inference time and model-instance accuracy not measured.\n")
    else:
        model = make_segmenter(f"model:{model_path}", threads=1)
        assert isinstance(model, OnnxSegmenter)
        floating, walls, floors = (sum(getattr(r, k) for r in runs) for k in ("floating", "walls", "floors"))
        parts += [
            *network_section(runs, names, model_path, model.input_size),
            "Network instances, 3D measurements (all seeds):\n",
            header,
            *learned.rows("network"),
            f"\nNetwork instances: {learned.unmatched} measurement(s) on no ground-truth object (< 50% of "
            f"the mask), {learned.skipped} skipped, {floating} left out for floating above the floor "
            f"(`floor_gap_m`), {walls} for lying on a surface taller than their class (`max_top_m`), "
            f"{floors} for lying flat on the floor (`min_top_m`).\n",
        ]
    if TUM.is_dir() and args.yolox.is_file():
        cv2.setNumThreads(1)
        parts += tum_monitor(args.yolox)
    else:
        parts.append(f"TUM part skipped: {TUM} or {args.yolox} absent.\n")
    body = "\n".join(parts)
    publish(body, args.write, "perception")
    return 0


if __name__ == "__main__":
    sys.exit(main())
