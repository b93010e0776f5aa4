"""Reference benchmark (issue 41): ORB-SLAM3 RGB-D against wardmap's tracker, same recordings.

ORB-SLAM3 runs through the ``pyorbslam3`` wheel (GPL-3.0: never a wardmap dependency, never
imported here) in the benchmark's own virtual environment (``--venv``, default
out/orbslam3-venv, created and filled with ``pip install pyorbslam3`` when absent), in a
subprocess (bench/_orbslam3_worker.py) fed the frames wardmap's ``DatasetReader`` reads, so
both systems see the same images. The two alternate in one session: per recording, ORB-SLAM3
then wardmap, ``--repeats`` times.

ORB-SLAM3 needs an ORB vocabulary in the DBoW2 text format; its published one is neither
shipped nor downloadable here, so ``--vocab`` is trained by wardmap's trainer
(``wardmap vocab train``, tools/vocabulary.py) on simulated frames of training worlds
(``--train-seeds``, below 1000), never on a recording evaluated here. Its settings YAML
(format 1.0) is written from each recording's calibration: pinhole + distortion, 1000 ORB
features on 8 levels (as wardmap), ``bf`` = 40 px (close points up to 40 baselines, ~3.1 m,
as wardmap's ``rgbd_bf``).

Reported per run: frames ORB-SLAM3 tracked (state OK), ATE (evo, SE3 alignment,
translation RMSE) and RPE (evo, translation, consecutive associated frames, RMSE) of the
trajectory each system writes (ORB-SLAM3's ``SaveTrajectoryTUM``), and the median
tracking-thread time per frame: ORB-SLAM3's ``track_rgbd`` call (its local mapping and loop
closing run on threads of their own), wardmap's whole frontend; wall clock and the thread's
CPU time. Not a test: nothing asserts a figure.

Needs Debian's libgl1 libegl1 libopengl0 libsm6 libice6 (the wheel's viewer links them).

    python bench/orbslam3.py [--repeats 2] [--seed 2001] [--scenarios aisle_slow_2 aisle_quick_3]
                             [--vocab-depth 6] [--vocab FILE] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import argparse
import ctypes.util
import json
import struct
import subprocess
import tempfile

import _one_core  # noqa: F401  (one thread per library, before numba and OpenCV load)
import cv2
import numpy as np
from _report import EVAL_SEEDS, git_rev, machine, publish

from wardmap.edge.offline import track_dataset
from wardmap.edge.tracker import TrackResult
from wardmap.shared.dataset import Calibration, DatasetReader, read_tum_trajectory
from wardmap.shared.metrics import ate, rpe
from wardmap.sim.runner import generate
from wardmap.tools.vocabulary import dataset_descriptors, train_vocabulary

ROOT = Path(__file__).resolve().parents[1]
TUM = ROOT.parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"
WORKER = Path(__file__).resolve().parent / "_orbslam3_worker.py"
PYORBSLAM3 = "pyorbslam3==0.1.1"
DEBIAN_LIBS = {"GL": "libgl1", "EGL": "libegl1", "OpenGL": "libopengl0", "SM": "libsm6", "ICE": "libice6"}
TRAIN_SCENARIOS = (("hospital_loop", 400), ("ward_chairs", 300))
"""Training recordings of the vocabulary: scenario and frames, on ``--train-seeds``."""
VOCAB_EVERY = 4
"""The vocabulary is trained on every 4th frame."""
RGBD_BF_PX = 40.0
ORB_FEATURES = 1000


def check_debian_libs() -> None:
    """Exit with the apt command when a shared library the wheel links is missing."""
    missing = [pkg for lib, pkg in DEBIAN_LIBS.items() if ctypes.util.find_library(lib) is None]
    if missing:
        raise SystemExit(f"pyorbslam3 needs Debian's {' '.join(missing)}: "
                         f"apt-get install -y {' '.join(DEBIAN_LIBS.values())}")


def ensure_venv(venv: Path) -> Path:
    """The python of ``venv`` with pyorbslam3 importable; creates and fills it when needed."""
    py = venv / "bin" / "python"
    if py.is_file() and subprocess.run([py, "-c", "import pyorbslam3"], capture_output=True).returncode == 0:
        return py
    print(f"creating {venv} with {PYORBSLAM3} (GPL, kept out of wardmap's environment) ...", file=sys.stderr)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    done = subprocess.run([py, "-m", "pip", "install", "-q", PYORBSLAM3])
    if done.returncode != 0:
        raise SystemExit(f"pip install {PYORBSLAM3} into {venv} failed (the wheel is manylinux x86-64, "
                         "CPython 3.9-3.13)")
    check = subprocess.run([py, "-c", "import pyorbslam3"], capture_output=True, text=True)
    if check.returncode != 0:
        raise SystemExit(f"pyorbslam3 does not import: {check.stderr.strip().splitlines()[-1]}")
    return py


def sim_recording(data: Path, scenario: str, seed: int) -> Path:
    """The cached simulated data set (bench/tracking.py's layout), rendered when absent."""
    out = data / f"{scenario}_s{seed}"
    if not (out / "sim.json").exists():
        print(f"generating {scenario} seed {seed} ...", file=sys.stderr)
        generate(scenario, seed, out, overwrite=True)
    return out


def training_recordings(data: Path, seeds: list[int]) -> list[Path]:
    """The vocabulary's simulated training recordings (:data:`TRAIN_SCENARIOS`), rendered when absent."""
    folders = []
    for seed in seeds:
        for scenario, frames in TRAIN_SCENARIOS:
            out = data / "vocab_train" / f"{scenario}_s{seed}_{frames}f"
            if not (out / "sim.json").exists():
                print(f"generating {scenario} seed {seed} ({frames} frames) ...", file=sys.stderr)
                generate(scenario, seed, out, frames=frames, overwrite=True)
            folders.append(out)
    return folders


def ensure_vocabulary(path: Path, folders: list[Path], k: int, depth: int) -> str:
    """Train a vocabulary on every :data:`VOCAB_EVERY`-th frame of ``folders`` unless ``path``
    exists (delete it to retrain); returns how it was made, for the table."""
    what = (f"k={k}, L={depth}, `wardmap vocab train --every {VOCAB_EVERY}` on "
            + ", ".join(f.name for f in folders))
    if path.is_file():
        return what
    print(f"training the ORB vocabulary {path} ...", file=sys.stderr)
    images = dataset_descriptors(folders, every=VOCAB_EVERY)
    voc = train_vocabulary(images, k=k, depth=depth, seed=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    voc.save(path)
    return what


def settings_yaml(calib: Calibration, fps: float) -> str:
    """ORB-SLAM3 settings (format 1.0) for an RGB-D camera; depth is sent in metres."""
    cam = calib.rgb
    k1, k2, p1, p2, k3 = cam.distortion
    baseline_m = RGBD_BF_PX / cam.fx
    return f"""%YAML:1.0
File.version: "1.0"
Camera.type: "PinHole"
Camera1.fx: {cam.fx!r}
Camera1.fy: {cam.fy!r}
Camera1.cx: {cam.cx!r}
Camera1.cy: {cam.cy!r}
Camera1.k1: {k1!r}
Camera1.k2: {k2!r}
Camera1.p1: {p1!r}
Camera1.p2: {p2!r}
Camera1.k3: {k3!r}
Camera.width: {cam.width}
Camera.height: {cam.height}
Camera.fps: {max(1, round(fps))}
Camera.RGB: 1
Stereo.ThDepth: 40.0
Stereo.b: {baseline_m!r}
RGBD.DepthMapFactor: 1.0
ORBextractor.nFeatures: {ORB_FEATURES}
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7
Viewer.KeyFrameSize: 0.05
Viewer.KeyFrameLineWidth: 1.0
Viewer.GraphLineWidth: 0.9
Viewer.PointSize: 2.0
Viewer.CameraSize: 0.08
Viewer.CameraLineWidth: 3.0
Viewer.ViewpointX: 0.0
Viewer.ViewpointY: -0.7
Viewer.ViewpointZ: -1.8
Viewer.ViewpointF: 500.0
"""


def score(traj: Path, reader: DatasetReader) -> tuple[float, float]:
    """(ATE cm, RPE cm/frame) of a TUM trajectory file against the recording's ground truth."""
    gt = reader.groundtruth()
    if gt is None:
        raise SystemExit(f"{reader.root}: no groundtruth.txt")
    st, T = read_tum_trajectory(traj)
    return 100 * ate(st, T, gt[0], gt[1]).rmse, 100 * rpe(st, T, gt[0], gt[1]).rmse


def drop_repeated_stamps(traj: Path) -> Path:
    """ORB-SLAM3's trajectory without the rows of lost frames, which it writes as copies of
    the row before (stamp included: its Tracking repeats the last frame time on a loss)."""
    rows, last = [], None
    for line in traj.read_text().splitlines():
        stamp = line.split(maxsplit=1)[0] if line.strip() else None
        if stamp is not None and stamp != last:
            rows.append(line)
            last = stamp
    out = traj.with_name(traj.stem + "_unique.txt")
    out.write_text("\n".join(rows) + "\n")
    return out


def run_orbslam3(py: Path, vocab: Path, reader: DatasetReader, tmp: Path) -> dict:
    """One ORB-SLAM3 run in the bench's venv; frames from ``reader`` over a pipe."""
    stamps = reader.stamps
    fps = 1.0 / float(np.median(np.diff(stamps))) if len(stamps) > 1 else 30.0
    settings = tmp / f"{reader.root.name}_orbslam3.yaml"
    settings.write_text(settings_yaml(reader.calibration, fps))
    traj = tmp / f"{reader.root.name}_orbslam3.txt"
    traj.unlink(missing_ok=True)
    cam = reader.calibration.rgb
    head = {"vocab": str(vocab), "settings": str(settings), "trajectory": str(traj),
            "frames": len(reader), "height": cam.height, "width": cam.width}
    log_path, out_path = tmp / "orbslam3.log", tmp / "orbslam3.json"
    # Output to files, not pipes: ORB-SLAM3 writes much to stdout/stderr while it reads frames.
    with log_path.open("wb") as log, out_path.open("wb") as result:
        proc = subprocess.Popen([py, str(WORKER)], stdin=subprocess.PIPE, stdout=result, stderr=log)
        assert proc.stdin is not None
        try:
            proc.stdin.write((json.dumps(head) + "\n").encode())
            for frame in reader:
                proc.stdin.write(struct.pack("<d", frame.stamp))
                proc.stdin.write(np.ascontiguousarray(frame.rgb, np.uint8).tobytes())
                proc.stdin.write(np.ascontiguousarray(frame.depth_m, np.float32).tobytes())
            proc.stdin.close()
        except BrokenPipeError:
            pass
        proc.wait()
    lines = out_path.read_text(errors="replace").strip().splitlines()
    if proc.returncode != 0 or not traj.is_file() or not lines:
        tail = log_path.read_text(errors="replace").strip().splitlines()[-5:]
        raise SystemExit(f"ORB-SLAM3 failed on {reader.root} (exit {proc.returncode}): " + " | ".join(tail))
    res = json.loads(lines[-1])
    a, r = score(drop_repeated_stamps(traj), reader)
    return {"ate_cm": a, "rpe_cm": r, "ok": sum(s == "OK" for s in res["states"]),
            "frames": len(res["states"]), "wall": float(np.median(res["wall_ms"])),
            "cpu": float(np.median(res["cpu_ms"]))}


def run_wardmap(reader: DatasetReader, tmp: Path) -> dict:
    """One run of wardmap's tracker out of the box (no calibration step, no labels)."""
    traj = tmp / f"{reader.root.name}_wardmap.txt"
    wall: list[float] = []
    cpu: list[float] = []

    def keep(_i: int, _n: int, result: TrackResult) -> None:
        wall.append(result.timings_ms["total"])
        cpu.append(result.timings_ms["cpu_total"])

    summary = track_dataset(reader.root, traj, labels="none", progress=keep)
    a, r = score(traj, reader)
    return {"ate_cm": a, "rpe_cm": r, "ok": summary["frames"] - summary["lost_frames"],
            "frames": summary["frames"], "wall": float(np.median(wall)), "cpu": float(np.median(cpu))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT / "out" / "bench_data",
                    help="cached simulated data sets")
    ap.add_argument("--venv", type=Path, default=ROOT / "out" / "orbslam3-venv", help="pyorbslam3's venv")
    ap.add_argument("--vocab", type=Path, help="DBoW2 text vocabulary (default "
                    "out/orbslam3/voc_sim_kK_LL.txt, trained on simulated training worlds when absent)")
    ap.add_argument("--vocab-k", type=int, default=10)
    ap.add_argument("--vocab-depth", type=int, default=6,
                    help="levels (default 6, as ORB-SLAM's own: it matches within the nodes 4 levels up)")
    ap.add_argument("--train-seeds", type=int, nargs="+", default=[1], help="vocabulary's worlds (< 1000)")
    ap.add_argument("--seed", type=int, default=EVAL_SEEDS[0], help="evaluation world of the scenarios")
    ap.add_argument("--scenarios", nargs="+", default=["aisle_slow_2", "aisle_quick_3"])
    ap.add_argument("--no-tum", action="store_true", help="skip the TUM excerpt")
    ap.add_argument("--repeats", type=int, default=2, help="alternating runs of each system per recording")
    ap.add_argument("--write", type=Path, help="update this markdown file's orbslam3 section")
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    if any(s >= 1000 for s in args.train_seeds):
        ap.error("--train-seeds must be training worlds (< 1000)")
    if args.seed in args.train_seeds:
        ap.error("--seed is a vocabulary training world: that would be a leak")
    cv2.setNumThreads(1)
    check_debian_libs()
    py = ensure_venv(args.venv)
    shape = f"k{args.vocab_k}_L{args.vocab_depth}"
    args.vocab = args.vocab or ROOT / "out" / "orbslam3" / f"voc_sim_{shape}.txt"
    sim_note = ensure_vocabulary(args.vocab, training_recordings(args.data, args.train_seeds),
                                 args.vocab_k, args.vocab_depth)
    notes = [f"Vocabulary `sim` (every ORB-SLAM3 row unless marked): {sim_note} (simulated training worlds, "
             "none of the recordings below)."]
    recordings = [(f"{s} seed {args.seed}", sim_recording(args.data, s, args.seed)) for s in args.scenarios]
    tum_vocab = args.vocab.with_name(f"voc_tum_excerpt_{shape}.txt")
    if not args.no_tum:
        if TUM.is_dir():
            recordings.insert(0, ("TUM fr1 rpy excerpt", TUM))
            tum_note = ensure_vocabulary(tum_vocab, [TUM], args.vocab_k, args.vocab_depth)
            notes.append(f"Vocabulary `tum`: {tum_note}, the evaluated recording itself: a leak, "
                         "reported apart only to show how much the vocabulary matters.")
        else:
            print(f"skip TUM: {TUM} absent", file=sys.stderr)
    rows = []
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        for label, folder in recordings:
            reader = DatasetReader(folder)
            systems = {"ORB-SLAM3 (sim)": args.vocab}
            if folder == TUM:
                systems["ORB-SLAM3 (tum: leak)"] = tum_vocab
            runs: dict[str, list[dict]] = {name: [] for name in [*systems, "wardmap"]}
            for k in range(args.repeats):
                for name in runs:
                    print(f"{label}: {name} run {k + 1} ...", file=sys.stderr)
                    r = (run_wardmap(reader, tmp) if name == "wardmap"
                         else run_orbslam3(py, systems[name], reader, tmp))
                    runs[name].append(r)
                    print(json.dumps(r), file=sys.stderr)
            ref = runs["ORB-SLAM3 (sim)"]
            ref_wall = float(np.median([r["wall"] for r in ref]))
            ref_cpu = float(np.median([r["cpu"] for r in ref]))
            for name, rs in runs.items():
                wall = float(np.median([r["wall"] for r in rs]))
                cpu = float(np.median([r["cpu"] for r in rs]))
                rows.append(f"| {label} | {name} | {_span(rs, 'ok', 'd')}/{rs[0]['frames']} "
                            f"| {_span(rs, 'ate_cm')} | {_span(rs, 'rpe_cm')} | {_span(rs, 'wall', '.1f')} "
                            f"| {_span(rs, 'cpu', '.1f')} | {wall / ref_wall:.2f} | {cpu / ref_cpu:.2f} |")
                print(rows[-1], file=sys.stderr)
    table = "\n".join([
        "| recording | system (vocabulary) | frames tracked | ATE RMSE cm | RPE cm/frame "
        "| tracking ms/frame, median (wall) | tracking CPU ms/frame, median | wall vs ORB-SLAM3 (sim) "
        "| CPU vs ORB-SLAM3 (sim) |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
    ])
    body = (
        "## Reference: ORB-SLAM3 RGB-D vs wardmap (issue 41)\n\n"
        f"Command: `python bench/orbslam3.py --repeats {args.repeats} --seed {args.seed} --scenarios "
        f"{' '.join(args.scenarios)} --vocab-depth {args.vocab_depth} --write BENCHMARKS.md`  \n"
        f"Machine: {machine()}; shared with other jobs, so times are upper bounds and wall clock is "
        f"inflated most; commit {git_rev()}.  \n"
        f"ORB-SLAM3: {PYORBSLAM3} (GPL, in its own venv, never a wardmap dependency), RGB-D, "
        f"{ORB_FEATURES} ORB features, its local mapping and loop closing on threads of their own; wardmap: "
        "`wardmap track` out of the box (no calibrate-readout, no labels), one core. Alternating in one "
        f"session, {args.repeats} runs of each per recording; ranges over the runs (ORB-SLAM3 is not "
        "deterministic).  \n"
        "ORB-SLAM3's published vocabulary (~1M words, trained on other images) is neither shipped nor "
        "downloadable here; ours are trained by wardmap's trainer (tools/vocabulary.py).  \n"
        "ATE: evo, SE3 alignment, translation RMSE of each system's written trajectory (ORB-SLAM3: "
        "SaveTrajectoryTUM). RPE: evo, translation between consecutive associated frames, RMSE. "
        "Times: per frame, ORB-SLAM3's tracking call and wardmap's whole frontend, wall clock and the "
        "calling thread's CPU time; ratios: median over runs, this row / ORB-SLAM3 (sim)."
        "\n\n" + table + "".join(f"\n\n{n}" for n in notes)
    )
    publish(body, args.write, "orbslam3")
    return 0


def _span(runs: list[dict], key: str, fmt: str = ".2f") -> str:
    """The range of ``key`` over runs, one value when they agree at this precision."""
    lo, hi = f"{min(r[key] for r in runs):{fmt}}", f"{max(r[key] for r in runs):{fmt}}"
    return lo if lo == hi else f"{lo}-{hi}"


if __name__ == "__main__":
    sys.exit(main())
