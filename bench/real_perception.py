"""Segmenters on real images (issue 42): false hospital objects and people in an office.

The TUM RGB-D excerpt ``../shared/data/tum_fr1_rpy_s3_first100`` (an office: desks, monitors,
chairs, a person, a wooden door; no hospital furniture) with our own annotations of a few
frames, ``bench/data/tum_fr1_rpy_labels.json`` (polygons drawn by us from the images; how is
stated in the file; the frames are used for no training). Per segmenter spec
(``make_segmenter``: the packaged network ``model``, ``yolox:PATH``, any ``PATH``):

- **hospital-only**: pixels given bed, wheelchair, cart, IV pole or temperature gun, on every
  frame of the excerpt (the office has none of them; goal <= 1 %), and door pixels outside the
  outlined door on the complete frames (goal: part of the same 1 %);
- **person outside people**: person pixels farther than ``--margin`` pixels from an outlined
  person, on the labelled frames (complete ones, and frames stated to hold no person; goal
  <= 0.5 %);
- **found**: per class (monitor, chair, desk, person, cup) on the complete frames, the objects
  of which at least ``--found`` of the outline carries the class, out of those outlined; and
  precision, the share of the class's pixels within ``--margin`` of an outline of the class.

    python bench/real_perception.py [--segmenter model] [--segmenter yolox:../shared/models/yolox_nano.onnx]
        [--data DIR] [--labels FILE] [--margin 12] [--found 0.25] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import _one_core  # noqa: F401  (one thread for numba, OpenMP, OpenBLAS)
import cv2
import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import git_rev, machine, publish

from wardmap.server.perception.models import make_segmenter
from wardmap.shared.dataset import DatasetReader

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"
LABELS = REPO / "bench" / "data" / "tum_fr1_rpy_labels.json"
YOLOX = REPO.parent / "shared" / "models" / "yolox_nano.onnx"
HOSPITAL_ONLY = ("bed", "wheelchair", "cart", "iv_pole", "temperature_gun")
"""Classes no office has. Doors are hospital-only too, but the office has one: scored apart."""
FOUND_CLASSES = ("wall_monitor", "chair", "desk", "person", "cup")


@dataclass
class Score:
    """Pixel and object counts of one segmenter."""

    frames: int = 0
    pixels: int = 0
    hospital_only: int = 0
    labelled_pixels: int = 0
    door_outside: int = 0
    complete_pixels: int = 0
    person_outside: int = 0
    found: dict[str, list[int]] = field(default_factory=lambda: {c: [0, 0] for c in FOUND_CLASSES})
    inside: dict[str, list[int]] = field(default_factory=lambda: {c: [0, 0] for c in FOUND_CLASSES})
    ms: list[float] = field(default_factory=list)


def polygon_mask(polygon: list[list[int]], shape: tuple[int, int]) -> NDArray[np.bool_]:
    """bool (H, W): the pixels inside ``polygon`` ([[x, y], ...], pixels)."""
    mask = np.zeros(shape, np.uint8)
    cv2.fillPoly(mask, [np.asarray(polygon, np.int32).reshape(-1, 2)], 1)
    return mask.astype(bool)


def grow(mask: NDArray[np.bool_], margin: int) -> NDArray[np.bool_]:
    """``mask`` dilated by ``margin`` pixels (the outlines' tolerance)."""
    if margin <= 0:
        return mask
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def load_labels(path: Path) -> dict[str, dict[str, Any]]:
    """Labelled frames by rgb file name (``rgb/<stamp>.png``)."""
    doc = json.loads(path.read_text())
    if doc.get("format_version") != 1:
        raise SystemExit(f"{path}: unsupported format_version {doc.get('format_version')!r}")
    return {f["rgb"]: f for f in doc["frames"]}


def score(spec: str, reader: DatasetReader, labels: dict[str, dict[str, Any]], margin: int,
          found_share: float) -> Score:
    seg = make_segmenter(spec, threads=1)
    names = seg.class_names
    index = {n: i for i, n in enumerate(names)}
    only = np.array([index[c] for c in HOSPITAL_ONLY])
    s = Score()
    for i in range(len(reader)):
        frame = reader.frame(i)
        key = f"rgb/{frame.stamp:.6f}.png"  # TUM names each colour image by its stamp
        bgr = np.ascontiguousarray(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
        started = time.perf_counter()
        out = seg.segment(bgr, frame.depth_m)
        s.ms.append((time.perf_counter() - started) * 1e3)
        cls = out.class_map
        s.frames += 1
        s.pixels += cls.size
        s.hospital_only += int(np.isin(cls, only).sum())
        label = labels.get(key)
        if label is None:
            continue
        shape = cls.shape
        person = cls == index["person"]
        if label["complete"]:
            outlines = {c: np.zeros(shape, bool) for c in (*FOUND_CLASSES, "door")}
            for obj in label["objects"]:
                region = polygon_mask(obj["polygon"], shape)
                outlines[obj["class"]] |= region
                if obj["class"] in FOUND_CLASSES:
                    counts = s.found[obj["class"]]
                    counts[1] += 1
                    counts[0] += int(np.mean(cls[region] == index[obj["class"]]) >= found_share)
            for c in FOUND_CLASSES:
                given = cls == index[c]
                s.inside[c][0] += int((given & grow(outlines[c], margin)).sum())
                s.inside[c][1] += int(given.sum())
            s.complete_pixels += cls.size
            s.door_outside += int(((cls == index["door"]) & ~grow(outlines["door"], margin)).sum())
            s.person_outside += int((person & ~grow(outlines["person"], margin)).sum())
            s.labelled_pixels += cls.size
        elif "person" in label.get("absent", ()):
            s.person_outside += int(person.sum())
            s.labelled_pixels += cls.size
    return s


def pct(a: int, b: int) -> str:
    return "-" if b == 0 else f"{100.0 * a / b:.2f}"


def table(results: list[tuple[str, Score]], labelled: int, complete: int, margin: int, found: float) -> str:
    lines = [
        "## Segmenters on real images: TUM fr1/rpy office (issue 42)",
        "",
        f"Machine: {machine()}; commit {git_rev()}. `python bench/real_perception.py --write BENCHMARKS.md` "
        f"(defaults: the packaged network and `yolox:../shared/models/yolox_nano.onnx`). All "
        f"100 frames of `tum_fr1_rpy_s3_first100`; {labelled} of them labelled by us "
        f"(`bench/data/tum_fr1_rpy_labels.json`: coarse polygons drawn from the images; {complete} "
        f"frames with every person, chair, desk, monitor, cup and door outlined, the others only "
        f"stated to hold no person); outlines widened by {margin} px. An object is found when "
        f"{found:.0%} of its outline carries its class.",
        "",
        "| segmenter | hospital-only px % (goal <= 1) | door px outside the door % "
        "| person px outside people % (goal <= 0.5) | monitors found | chairs found | desks found "
        "| people found | cups found "
        "| precision % monitor / chair / desk / person / cup | ms per frame median |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for spec, s in results:
        found_cells = [f"{s.found[c][0]} / {s.found[c][1]}" for c in FOUND_CLASSES]
        precision = " / ".join(pct(*s.inside[c]) for c in FOUND_CLASSES)
        lines.append(
            f"| `{spec}` | {pct(s.hospital_only, s.pixels)} | {pct(s.door_outside, s.complete_pixels)} | "
            f"{pct(s.person_outside, s.labelled_pixels)} | {' | '.join(found_cells)} | {precision} | "
            f"{float(np.median(s.ms)):.1f} |"
        )
    lines += [
        "",
        "Hospital-only = bed, wheelchair, cart, IV pole, temperature gun on all frames; a door outside "
        "the outlined wooden door counts in its own column (complete frames). Precision: share of a "
        "class's pixels within an outline of that class (complete frames); '-' where none was given.",
    ]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--segmenter", action="append", metavar="SPEC",
                    help="segmenter spec, repeatable (default: model and "
                    "yolox:../shared/models/yolox_nano.onnx)")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--labels", type=Path, default=LABELS)
    ap.add_argument("--margin", type=int, default=12, help="outline tolerance, pixels")
    ap.add_argument("--found", type=float, default=0.25, help="share of an outline that must carry the class")
    ap.add_argument("--write", type=Path, metavar="BENCHMARKS.md")
    args = ap.parse_args()
    if not args.data.is_dir():
        raise SystemExit(f"data set not found: {args.data}")
    specs = args.segmenter or ["model", f"yolox:{YOLOX}"]
    labels = load_labels(args.labels)
    reader = DatasetReader(args.data)
    missing = sorted(set(labels) - {f"rgb/{t:.6f}.png" for t in reader.stamps})
    if missing:
        raise SystemExit(f"{args.labels}: labelled frames not in {args.data}: {', '.join(missing)}")
    results = [(spec, score(spec, reader, labels, args.margin, args.found)) for spec in specs]
    shown = [(spec.replace(str(REPO.parent), ".."), s) for spec, s in results]
    complete = sum(1 for f in labels.values() if f["complete"])
    publish(table(shown, len(labels), complete, args.margin, args.found), args.write, "real_perception")
    return 0


if __name__ == "__main__":
    sys.exit(main())
