"""Read the 256 rBRIEF test pairs out of OpenCV's ORB and write ``edge/orb_pattern.py``.

The pairs are ORB's learned pattern (Rublee et al., ICCV 2011) as OpenCV ships it
(Apache-2.0). They are found by asking ``cv2.ORB.compute`` for the descriptor of a keypoint
at angle 0 on random images: each bit is ``B(p1) < B(p2)`` on the blurred image ``B``, so
the one pair of patch offsets whose comparisons agree with a bit on every image is that
bit's pair. ``tests/edge/test_features.py`` checks descriptors against ``cv2.ORB`` bit for
bit, so a different OpenCV fails there, not silently.

Usage: ``python scripts/derive_orb_pattern.py [--out edge/orb_pattern.py]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

HALF = 15  # patch radius searched (the pattern lies within +-13)
GROUPS = 4  # 64 random images per group: enough to make every bit's pair unique
SIZE = 121


def derive(seed: int = 1) -> np.ndarray:
    """(256, 4) int8: x1, y1, x2, y2 of each bit's pair (bit k of byte k // 8, LSB first)."""
    cv2.setNumThreads(1)
    orb = cv2.ORB.create(nfeatures=10, edgeThreshold=19, patchSize=31)
    rng = np.random.default_rng(seed)
    c = SIZE // 2
    offs = [(dx, dy) for dy in range(-HALF, HALF + 1) for dx in range(-HALF, HALF + 1)]
    n_off = len(offs)
    kernel = cv2.getGaussianKernel(7, 2, ktype=cv2.CV_32F)
    agree = np.ones((256, n_off, n_off), np.bool_)
    for _ in range(GROUPS):
        seen = np.zeros(256, np.uint64)
        packed = np.zeros((n_off, n_off), np.uint64)
        for n in range(64):
            img = rng.integers(0, 256, (SIZE, SIZE), dtype=np.uint8)
            _, desc = orb.compute(img, [cv2.KeyPoint(float(c), float(c), 31.0, 0.0, 1.0, 0, 0)])
            if desc is None or len(desc) != 1:
                raise SystemExit("cv2.ORB.compute dropped the probe keypoint")
            seen |= np.unpackbits(desc[0], bitorder="little").astype(np.uint64) << np.uint64(n)
            blurred = cv2.sepFilter2D(img, cv2.CV_8U, kernel, kernel, borderType=cv2.BORDER_REFLECT_101)
            v = np.array([blurred[c + dy, c + dx] for dx, dy in offs], np.int32)
            packed |= (v[:, None] < v[None, :]).astype(np.uint64) << np.uint64(n)
        for k in range(256):
            agree[k] &= packed == seen[k]
    pattern = np.zeros((256, 4), np.int8)
    for k in range(256):
        hits = np.argwhere(agree[k])
        if len(hits) != 1:
            raise SystemExit(
                f"bit {k}: {len(hits)} candidate pairs (expected 1); is ORB's blur still 7x7, sigma 2?"
            )
        i, j = hits[0]
        pattern[k] = (*offs[i], *offs[j])
    return pattern


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parents[1] / "edge" / "orb_pattern.py"
    )
    args = ap.parse_args(argv)
    pattern = derive()
    rows = ",\n".join("    (" + ", ".join(str(int(v)) for v in row) + ")" for row in pattern)
    args.out.write_text(
        '"""ORB\'s 256 rBRIEF test pairs (Rublee et al., ICCV 2011), as OpenCV\'s ORB uses them.\n\n'
        "Row k: x1, y1, x2, y2 (pixels from the keypoint, before rotation by its angle); bit k\n"
        "of a descriptor (byte k // 8, least significant bit first) is B(p1) < B(p2) on the\n"
        "blurred level image B. Read from cv2 (OpenCV, Apache-2.0) by\n"
        "``scripts/derive_orb_pattern.py``; do not edit by hand.\n"
        '"""\n\n'
        f"ORB_PATTERN: tuple[tuple[int, int, int, int], ...] = (\n{rows},\n)\n",
        encoding="utf-8",
    )
    print(f"wrote {args.out} ({len(pattern)} pairs, cv2 {cv2.__version__})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
