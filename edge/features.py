"""Feature extraction and descriptor matching for the edge tracking frontend.

Two extractors, as in paper 003:

- ORB on the RGB (grey) image, distributed over a grid (paper 003 Sec. IV-C, Eq. 3-5):
  each cell of a ``grid_cols x grid_rows`` grid gets a quota of corners (Eq. 3) inside
  its borders (Eq. 4); FAST corners (the oFAST segment test, Eq. 5) are ranked by their
  Harris response and the strongest kept (Step 4). This runs on every level of an image
  pyramid; orientation (intensity centroid) and rBRIEF descriptors are ORB's.
- SIFT on thermal images with an adaptive contrast threshold (paper 003 Sec. IV-C):
  lower the threshold by 0.005 until at least 800 points are found.

Matching: brute-force Hamming / L2 with Lowe's ratio test (:func:`match_descriptors`) and
a guided matcher for map points projected into the frame (:func:`match_projected`).

Pixel coordinates ``(u, v)`` are those of the image as captured (distorted), the centre
of the top-left pixel at (0, 0), u along columns. Everything runs on one core; cv2
objects are created once per extractor (:class:`OrbExtractor`), not per frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple, cast

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from wardmap.edge.orb_pattern import ORB_PATTERN
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.hamming import popcount64

FeatureKind = Literal["orb", "sift"]

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]

ORB_DESCRIPTOR_BYTES = 32
SIFT_DESCRIPTOR_LEN = 128
_ORB_PATCH_SIZE = 31  # rBRIEF patch; the intensity-centroid radius is half of it
_HARRIS_BLOCK = 7  # Harris window of ORB (OpenCV's HarrisResponses)
_HARRIS_K = 0.04
# The 512 rBRIEF test points (float32, pixels from the corner): p1 of bit k at 2k, p2 at 2k + 1.
_PATTERN_X = np.array(ORB_PATTERN, np.float32)[:, [0, 2]].ravel()
_PATTERN_Y = np.array(ORB_PATTERN, np.float32)[:, [1, 3]].ravel()
_PATTERN_REACH = 18  # px: the farthest a rotated test point lies from its corner (13 sqrt 2, rounded)
_DEG2RAD_F32 = np.float32(math.pi / 180.0)  # OpenCV ORB's factorPI, a float
_BLUR_KERNEL = cv2.getGaussianKernel(7, 2, ktype=cv2.CV_32F)  # ORB's 7x7, sigma 2 smoothing


# --------------------------------------------------------------------------- containers


@dataclass(frozen=True)
class Features:
    """Keypoints and descriptors of one image.

    Attributes:
        uv: (N, 2) float32 pixel coordinates in the image as captured (distorted), at
            pyramid level 0 whatever level the keypoint was found on.
        angle_deg: (N,) float32 keypoint orientation in degrees, [0, 360).
        response: (N,) float32 detector score (ORB: Harris response, paper 003 Step 4;
            SIFT: DoG contrast).
        octave: (N,) int32 pyramid level (ORB: 0 = full resolution, scale
            ``scale_factor**octave``; SIFT: OpenCV's octave, -1 for the upsampled one).
        size: (N,) float32 diameter of the keypoint's support region in level-0 pixels.
        descriptors: (N, 32) uint8 rBRIEF for ORB, (N, 128) float32 for SIFT.
        kind: ``"orb"`` or ``"sift"``.
    """

    uv: F32
    angle_deg: F32
    response: F32
    octave: NDArray[np.int32]
    size: F32
    descriptors: NDArray[np.uint8] | NDArray[np.float32]
    kind: FeatureKind

    def __post_init__(self) -> None:
        n = self.uv.shape[0]
        if self.uv.ndim != 2 or self.uv.shape[1] != 2:
            raise GeometryError(f"Features.uv: expected (N, 2), got {self.uv.shape}")
        for name in ("angle_deg", "response", "octave", "size"):
            arr = getattr(self, name)
            if arr.shape != (n,):
                raise GeometryError(f"Features.{name}: expected ({n},), got {arr.shape}")
        want = (n, ORB_DESCRIPTOR_BYTES) if self.kind == "orb" else (n, SIFT_DESCRIPTOR_LEN)
        dtype = np.uint8 if self.kind == "orb" else np.float32
        if self.descriptors.shape != want or self.descriptors.dtype != dtype:
            raise GeometryError(
                f"Features.descriptors ({self.kind}): expected {want} {np.dtype(dtype)}, "
                f"got {self.descriptors.shape} {self.descriptors.dtype}"
            )

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    def select(self, which: NDArray[np.bool_] | NDArray[np.intp]) -> Features:
        """The features picked by a boolean mask (N,) or an index array, in that order."""
        return Features(
            self.uv[which],
            self.angle_deg[which],
            self.response[which],
            self.octave[which],
            self.size[which],
            self.descriptors[which],
            self.kind,
        )

    @staticmethod
    def empty(kind: FeatureKind) -> Features:
        """No features (e.g. a blank frame)."""
        descriptors: NDArray[np.uint8] | NDArray[np.float32] = (
            np.zeros((0, ORB_DESCRIPTOR_BYTES), np.uint8)
            if kind == "orb"
            else np.zeros((0, SIFT_DESCRIPTOR_LEN), np.float32)
        )
        return Features(
            uv=np.zeros((0, 2), np.float32),
            angle_deg=np.zeros(0, np.float32),
            response=np.zeros(0, np.float32),
            octave=np.zeros(0, np.int32),
            size=np.zeros(0, np.float32),
            descriptors=descriptors,
            kind=kind,
        )


@dataclass(frozen=True)
class OrbConfig:
    """Grid-distributed ORB (paper 003 Eq. 3-5, ORB-SLAM2's extractor)."""

    n_features: int = 1000
    """Q, the total number of features wanted per frame (fewer if the image lacks corners)."""
    grid_cols: int = 8
    """G_col, grid columns (paper 003 Eq. 3-4)."""
    grid_rows: int = 6
    """G_row, grid rows. Each cell's quota is Q / (G_col * G_row) (Eq. 3), shared over levels."""
    fast_threshold: int = 20
    """FAST intensity threshold (grey levels) tried first in every cell."""
    min_fast_threshold: int = 7
    """Lower FAST threshold whose corners fill a cell that the first threshold leaves
    below its quota (ORB-SLAM2's iniThFAST / minThFAST). The largest single cost of
    extraction: raising it to 10 saves about 10 % of the time on TUM frames."""
    n_levels: int = 8
    """Pyramid levels; level l is the image scaled by 1 / scale_factor**l."""
    scale_factor: float = 1.2
    """Scale ratio between consecutive pyramid levels."""
    edge_margin: int = 19
    """Pixels (at each level) next to the border where no keypoint is detected; at
    least 16 so the orientation patch (radius 15) fits. ORB-SLAM2 uses 19."""
    harris_ranking: bool = True
    """Rank corners inside a cell by Harris response (paper 003 Step 4); False ranks by
    FAST score instead (slightly faster, not the paper's choice)."""

    def __post_init__(self) -> None:
        if self.n_features <= 0:
            raise ConfigError(f"OrbConfig.n_features must be positive, got {self.n_features}")
        if self.grid_cols <= 0 or self.grid_rows <= 0:
            raise ConfigError(f"OrbConfig grid must be positive, got {self.grid_cols}x{self.grid_rows}")
        if not 1 <= self.min_fast_threshold <= self.fast_threshold <= 255:
            raise ConfigError(
                "OrbConfig: need 1 <= min_fast_threshold <= fast_threshold <= 255, got "
                f"{self.min_fast_threshold}, {self.fast_threshold}"
            )
        if not 1 <= self.n_levels <= 16:
            raise ConfigError(f"OrbConfig.n_levels must be in 1..16, got {self.n_levels}")
        if not 1.0 < self.scale_factor <= 2.0:
            raise ConfigError(f"OrbConfig.scale_factor must be in (1, 2], got {self.scale_factor}")
        if self.edge_margin < _ORB_PATCH_SIZE // 2 + 1:
            raise ConfigError(f"OrbConfig.edge_margin must be >= 16, got {self.edge_margin}")


@dataclass(frozen=True)
class SiftConfig:
    """Adaptive-contrast SIFT for thermal images (paper 003 Sec. IV-C)."""

    min_features: int = 800
    """Lower the contrast threshold until at least this many keypoints (paper: 800)."""
    initial_contrast: float = 0.04
    """First contrast threshold (OpenCV's / Lowe's default)."""
    contrast_step: float = 0.005
    """Decrement per retry (paper: 0.005)."""
    min_contrast: float = 0.005
    """Lowest threshold tried; bounds the loop."""
    max_features: int = 1500
    """Keep at most this many keypoints, the strongest by response."""
    n_octave_layers: int = 3
    """SIFT layers per octave (Lowe's 3)."""
    edge_threshold: float = 10.0
    """SIFT's principal-curvature (edge) threshold; paper 003 finds it matters little."""

    def __post_init__(self) -> None:
        if not 0 < self.min_features <= self.max_features:
            raise ConfigError(
                f"SiftConfig: need 0 < min_features <= max_features, got {self.min_features}, "
                f"{self.max_features}"
            )
        if not 0 < self.min_contrast <= self.initial_contrast:
            raise ConfigError(
                f"SiftConfig: need 0 < min_contrast <= initial_contrast, got {self.min_contrast}, "
                f"{self.initial_contrast}"
            )
        if self.contrast_step <= 0:
            raise ConfigError(f"SiftConfig.contrast_step must be positive, got {self.contrast_step}")


# --------------------------------------------------------------------------- ORB kernels


def _orb_umax(half_patch: int) -> NDArray[np.int32]:
    """Half-widths (half_patch + 1,) of ORB's circular orientation patch, row by row.

    Same construction as OpenCV's ORB / ORB-SLAM2 (made symmetric in u and v).
    """
    umax = np.zeros(half_patch + 2, np.int32)
    vmax = math.floor(half_patch * math.sqrt(2.0) / 2 + 1)
    vmin = math.ceil(half_patch * math.sqrt(2.0) / 2)
    for v in range(vmax + 1):
        umax[v] = round(math.sqrt(half_patch * half_patch - v * v))
    v0 = 0
    for v in range(half_patch, vmin - 1, -1):
        while umax[v0] == umax[v0 + 1]:
            v0 += 1
        umax[v] = v0
        v0 += 1
    return umax[: half_patch + 1]


@njit(cache=True, nogil=True)
def _harris_response(img: NDArray[np.uint8], xy: NDArray[np.int32]) -> NDArray[np.float32]:
    """Harris response (n,) at integer pixels (n, 2) of one pyramid level (paper 003 Step 4).

    7x7 window of 3x3 Sobel gradients, k = 0.04, scaled like OpenCV's ORB
    (``HarrisResponses``). The caller keeps points at least 4 px inside the image.
    """
    n = xy.shape[0]
    out = np.zeros(n, np.float32)
    r = _HARRIS_BLOCK // 2
    scale = 1.0 / (4.0 * _HARRIS_BLOCK * 255.0)
    scale4 = scale * scale * scale * scale
    for i in range(n):
        x = xy[i, 0]
        y = xy[i, 1]
        a = 0
        b = 0
        c = 0
        for yy in range(y - r, y + r + 1):
            for xx in range(x - r, x + r + 1):
                tl = int(img[yy - 1, xx - 1])
                tc = int(img[yy - 1, xx])
                tr = int(img[yy - 1, xx + 1])
                ml = int(img[yy, xx - 1])
                mr = int(img[yy, xx + 1])
                bl = int(img[yy + 1, xx - 1])
                bc = int(img[yy + 1, xx])
                br = int(img[yy + 1, xx + 1])
                ix = 2 * (mr - ml) + (tr - tl) + (br - bl)
                iy = 2 * (bc - tc) + (bl - tl) + (br - tr)
                a += ix * ix
                b += iy * iy
                c += ix * iy
        fa = float(a)
        fb = float(b)
        fc = float(c)
        out[i] = (fa * fb - fc * fc - _HARRIS_K * (fa + fb) * (fa + fb)) * scale4
    return out


@njit(cache=True, nogil=True)
def _ic_angle(img: NDArray[np.uint8], xy: NDArray[np.int32], umax: NDArray[np.int32]) -> NDArray[np.float32]:
    """Orientation in degrees [0, 360) by intensity centroid (Rublee et al. 2011, ORB).

    ``atan2(m01, m10)`` of the circular patch of radius ``len(umax) - 1`` around each
    integer pixel (n, 2); same sums as OpenCV's ``ICAngles``. The caller keeps points at
    least that radius + 1 inside the image.
    """
    n = xy.shape[0]
    out = np.zeros(n, np.float32)
    half = umax.shape[0] - 1
    for i in range(n):
        x = xy[i, 0]
        y = xy[i, 1]
        m10 = 0
        m01 = 0
        for u in range(-half, half + 1):
            m10 += u * int(img[y, x + u])
        for v in range(1, half + 1):
            vsum = 0
            d = umax[v]
            for u in range(-d, d + 1):
                plus = int(img[y + v, x + u])
                minus = int(img[y - v, x + u])
                vsum += plus - minus
                m10 += u * (plus + minus)
            m01 += v * vsum
        deg = math.degrees(math.atan2(float(m01), float(m10)))
        if deg < 0.0:
            deg += 360.0
        if deg >= 360.0:
            deg -= 360.0
        out[i] = deg
    return out


@njit(cache=True, nogil=True)
def _rbrief(img: U8, xy: NDArray[np.int32], angle_deg: F32, px: F32, py: F32, out: U8, first: int) -> None:
    """rBRIEF descriptors of keypoints of one blurred level into ``out[first:first + n]``.

    ``img`` (h, w) uint8 is the level smoothed by ORB's 7x7, sigma 2 Gaussian; ``xy`` (n, 2)
    int32 the keypoints in level pixels; ``angle_deg`` (n,) float32 their orientation;
    ``px, py`` (2 n_bits,) float32 the test points, p1 and p2 of bit k at 2k and 2k + 1.
    Bit k is ``img[p1] < img[p2]`` with both points rotated by the angle (steered BRIEF,
    paper 003's rBRIEF), rounded to the nearest pixel in float32 arithmetic as OpenCV's ORB
    does, so the bits are OpenCV's.
    """
    n_bits = px.shape[0] // 2
    magic = np.float32(12582912.0)  # 1.5 * 2**23: (x + magic) - magic rounds half to even
    flat = img.ravel()
    step = img.shape[1]
    offset = np.empty(2 * n_bits, np.int64)
    for i in range(xy.shape[0]):
        ang = np.float32(angle_deg[i]) * _DEG2RAD_F32
        a = np.float32(math.cos(np.float64(ang)))
        b = np.float32(math.sin(np.float64(ang)))
        for k in range(2 * n_bits):
            u = ((px[k] * a - py[k] * b) + magic) - magic
            v = ((px[k] * b + py[k] * a) + magic) - magic
            offset[k] = np.int64(v) * step + np.int64(u)
        centre = np.int64(xy[i, 1]) * step + xy[i, 0]
        row = out[first + i]
        for byte in range(n_bits // 8):
            val = 0
            for j in range(8):
                k = 2 * (byte * 8 + j)
                if flat[centre + offset[k]] < flat[centre + offset[k + 1]]:
                    val |= 1 << j
            row[byte] = val


def _level_quotas(cfg: OrbConfig) -> F64:
    """Features wanted per pyramid level (n_levels,), summing to n_features.

    Geometric in 1 / scale_factor as in ORB-SLAM2 and OpenCV's ORB: level l gets
    Q (1 - f) / (1 - f^L) f^l with f = 1 / scale_factor.
    """
    f = 1.0 / cfg.scale_factor
    lv = np.arange(cfg.n_levels, dtype=np.float64)
    if cfg.n_levels == 1:
        return np.array([float(cfg.n_features)])
    return cfg.n_features * (1 - f) / (1 - f**cfg.n_levels) * f**lv


def _water_fill(available: I64, quota: F64, target: int) -> I64:
    """Integer allotments k_b <= available_b, summing to min(target, sum available).

    Every bin gets ``min(available_b, lam * quota_b)`` for the one scalar ``lam`` that
    meets the target: quota that a bin cannot use (too few corners) is spread over the
    other bins in proportion to their own quota, so no bin exceeds ``lam`` times its
    quota. Rounding remainders go to bins with the largest fractional share.
    """
    avail = available.astype(np.float64)
    total = int(available.sum())
    if total <= target:
        return available.copy()
    ratio = np.where(quota > 0, avail / np.maximum(quota, 1e-12), np.inf)
    order = np.argsort(ratio, kind="stable")
    r_sorted = ratio[order]
    n_sorted = avail[order]
    q_sorted = quota[order]
    # f(lam) at each breakpoint r_j: bins <= j are saturated, the rest give lam * q.
    sat = np.cumsum(n_sorted)
    q_rest = q_sorted.sum() - np.cumsum(q_sorted)
    f_at = sat + r_sorted * q_rest
    j = int(np.searchsorted(f_at, target, side="left"))
    sat_before = sat[j - 1] if j > 0 else 0.0
    q_free = q_sorted[j:].sum()
    lam = (target - sat_before) / q_free if q_free > 0 else 0.0
    share = np.minimum(avail, lam * quota)
    alloc = np.floor(share + 1e-9).astype(np.int64)
    short = target - int(alloc.sum())
    if short > 0:
        frac = np.where(alloc < available, share - alloc, -1.0)
        extra = np.argsort(-frac, kind="stable")[:short]
        alloc[extra[frac[extra] > -1.0]] += 1
    return alloc


@njit(cache=True, nogil=True)
def _select_in_bins(
    bin_id: I64, low: NDArray[np.bool_], score: F32, alloc: I64, small_int_score: bool
) -> I64:
    """Indices (sorted) of the points each bin keeps: ``alloc[b]`` per bin ``b``.

    Inside a bin, points with ``low`` False (the fast_threshold tier) come first, then
    the low tier fills what is left; within a tier the highest ``score`` wins (paper 003
    Step 4); ties go to the lower index. ``small_int_score``: scores are integers in
    0..255 (FAST scores), ordered by a counting sort instead of a comparison sort.
    """
    n = bin_id.shape[0]
    if small_int_score:
        hist = np.zeros(257, np.int64)
        for i in range(n):
            hist[255 - min(max(int(score[i]), 0), 255) + 1] += 1
        for k in range(256):
            hist[k + 1] += hist[k]
        order = np.empty(n, np.int64)
        for i in range(n):
            key = 255 - min(max(int(score[i]), 0), 255)
            order[hist[key]] = i
            hist[key] += 1
    else:
        order = np.argsort(-score, kind="mergesort")
    taken = np.zeros(alloc.shape[0], np.int64)
    keep = np.zeros(n, np.bool_)
    for tier in range(2):
        want_low = tier == 1
        for k in range(n):
            i = order[k]
            if low[i] != want_low:
                continue
            b = bin_id[i]
            if taken[b] < alloc[b]:
                taken[b] += 1
                keep[i] = True
    return np.nonzero(keep)[0].astype(np.int64)


class OrbExtractor:
    """Grid-distributed ORB over an image pyramid; holds the cv2 objects between frames.

    Not thread-safe: use one extractor per thread. Per frame:

    1. Pyramid of ``n_levels`` levels (bilinear, each from the previous one). On every
       level, FAST corners (the oFAST segment test, paper 003 Eq. 5, with non-maximum
       suppression) at least ``edge_margin`` px from the level's border, detected once
       at ``min_fast_threshold``: a corner whose FAST score reaches ``fast_threshold`` is
       exactly one a detection at ``fast_threshold`` would give, so the one pass serves
       both thresholds.
    2. Each corner falls in a cell of the grid (Eq. 4: cell borders at i w / G_col and
       j h / G_row of the level-0 image). A (level, cell) bin has the quota
       Q_level / (G_col G_row) (Eq. 3; Q_level geometric over levels as in ORB-SLAM2).
    3. Quota that bins short of corners cannot use goes to the others
       (:func:`_water_fill`), so the frame gets close to Q features while a cell exceeds
       its share only by that redistribution.
    4. Inside a bin the ``fast_threshold`` corners come first and the low-threshold ones
       only fill what they leave (ORB-SLAM2's per-cell fallback, Step 3). A bin with
       more corners than its allotment keeps the strongest by Harris response (Step 4),
       evaluated, as in OpenCV's ORB, on the best 2x allotment by FAST score.
    5. Orientation by intensity centroid, then rBRIEF descriptors (:func:`_rbrief`) on
       OpenCV ORB's own smoothed pyramid (:meth:`_orb_levels`): the bits ``cv2.ORB.compute``
       gives for these keypoints, which the shipped vocabularies were trained on, without
       building a cv2.KeyPoint per corner.
    """

    def __init__(self, cfg: OrbConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else OrbConfig()
        self._fast = cv2.FastFeatureDetector.create(
            threshold=self.cfg.min_fast_threshold,
            nonmaxSuppression=True,
            type=cv2.FAST_FEATURE_DETECTOR_TYPE_9_16,
        )
        self._umax = _orb_umax(_ORB_PATCH_SIZE // 2)
        # Below the reach, tests read pixels outside the level (cv2: its reflected border).
        self._pad = max(0, _PATTERN_REACH - self.cfg.edge_margin)
        self._n_cells = self.cfg.grid_cols * self.cfg.grid_rows
        # Eq. 3: quota of every (level, cell) bin, level-major.
        self._bin_quota = np.repeat(_level_quotas(self.cfg) / self._n_cells, self._n_cells)
        self._scales = self.cfg.scale_factor ** np.arange(self.cfg.n_levels, dtype=np.float64)

    def _pyramid(self, gray: U8) -> list[U8]:
        """Levels of the image, each resized (bilinear) from the previous one like ORB-SLAM2's."""
        h, w = gray.shape
        levels = [gray]
        for lv in range(1, self.cfg.n_levels):
            s = self._scales[lv]
            size = (round(w / s), round(h / s))
            if min(size) <= 2 * self.cfg.edge_margin + 1:
                break
            levels.append(cast(U8, cv2.resize(levels[-1], size, interpolation=cv2.INTER_LINEAR)))
        return levels

    def _corners(self, img: U8) -> tuple[NDArray[np.int32], F32]:
        """FAST corners (n, 2) int32 of one level, in level pixels, and their FAST scores (n,).

        Only corners at least ``edge_margin`` px inside; the segment test itself needs 3 px
        around a corner, so the ROI handed to cv2 is 3 px larger than that.
        """
        m = self.cfg.edge_margin
        lh, lw = img.shape
        kps = self._fast.detect(img[m - 3 : lh - m + 3, m - 3 : lw - m + 3], None)
        if not kps:
            return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
        xy = np.asarray(cv2.KeyPoint.convert(kps), np.float32).astype(np.int32) + (m - 3)
        score = np.array([k.response for k in kps], np.float32)
        inside = (xy[:, 0] >= m) & (xy[:, 0] < lw - m) & (xy[:, 1] >= m) & (xy[:, 1] < lh - m)
        if not inside.all():
            xy, score = xy[inside], score[inside]
        return xy, score

    def extract(self, gray: U8, mask: U8 | None = None) -> Features:
        """ORB features of a grey image.

        Args:
            gray: (H, W) uint8 image.
            mask: optional (H, W) uint8; keypoints only where it is non-zero (tested at
                their level-0 pixel).

        Returns:
            Features of kind ``"orb"`` ordered by pyramid level, at most ``n_features``;
            none (not an error) for a blank or tiny image.

        Raises:
            GeometryError: wrong dtype or shape of ``gray`` or ``mask``.
        """
        if not isinstance(gray, np.ndarray) or gray.dtype != np.uint8 or gray.ndim != 2:
            shape = getattr(gray, "shape", None)
            raise GeometryError(
                f"extract_orb: expected a (H, W) uint8 image, got {shape} {getattr(gray, 'dtype', None)}"
            )
        if mask is not None and (
            not isinstance(mask, np.ndarray) or mask.shape != gray.shape or mask.dtype != np.uint8
        ):
            raise GeometryError(
                f"extract_orb: mask must be uint8 {gray.shape}, got {getattr(mask, 'dtype', None)} "
                f"{getattr(mask, 'shape', None)}"
            )
        cfg = self.cfg
        h, w = gray.shape
        m = cfg.edge_margin
        if h <= 2 * m + 1 or w <= 2 * m + 1:
            return Features.empty("orb")
        pyramid = self._pyramid(gray)

        # Step 1 / Eq. 5: FAST corners of every level.
        xy_parts: list[NDArray[np.int32]] = []
        score_parts: list[F32] = []
        level_parts: list[I64] = []
        for lv, img in enumerate(pyramid):
            xy, score = self._corners(img)
            xy_parts.append(xy)
            score_parts.append(score)
            level_parts.append(np.full(xy.shape[0], lv, np.int64))
        xy_all = np.concatenate(xy_parts)
        fast = np.concatenate(score_parts)
        level = np.concatenate(level_parts)
        uv0 = xy_all * self._scales[level][:, None]
        if mask is not None and uv0.shape[0]:
            u0 = np.minimum(np.rint(uv0[:, 0]).astype(np.int64), w - 1)
            v0 = np.minimum(np.rint(uv0[:, 1]).astype(np.int64), h - 1)
            ok = mask[v0, u0] != 0
            xy_all, fast, level, uv0 = xy_all[ok], fast[ok], level[ok], uv0[ok]
        if uv0.shape[0] == 0:
            return Features.empty("orb")

        # Step 2 / Eq. 4: the cell of each corner from its level-0 position; bins are
        # level-major, so anything sorted by bin is sorted by level.
        col = np.minimum((uv0[:, 0] * (cfg.grid_cols / w)).astype(np.int64), cfg.grid_cols - 1)
        row = np.minimum((uv0[:, 1] * (cfg.grid_rows / h)).astype(np.int64), cfg.grid_rows - 1)
        bin_id = level * self._n_cells + row * cfg.grid_cols + col
        # Eq. 3 + redistribution of unused quota.
        available = np.bincount(bin_id, minlength=self._bin_quota.shape[0]).astype(np.int64)
        alloc = _water_fill(available, self._bin_quota, cfg.n_features)

        # Steps 3-4: strongest corners per bin, fast_threshold tier first.
        low = fast < cfg.fast_threshold
        if cfg.harris_ranking:
            # Harris only on the best 2x allotment by FAST score (OpenCV ORB's pre-filter).
            cand = _select_in_bins(bin_id, low, fast, 2 * alloc, True)
            harris = np.empty(cand.shape[0], np.float32)
            bounds = np.searchsorted(level[cand], np.arange(len(pyramid) + 1), side="left")
            for lv in range(len(pyramid)):
                a, b = bounds[lv], bounds[lv + 1]
                if b > a:
                    harris[a:b] = _harris_response(pyramid[lv], np.ascontiguousarray(xy_all[cand[a:b]]))
            sub = _select_in_bins(bin_id[cand], low[cand], harris, alloc, False)
            keep = cand[sub]
            response = harris[sub]
        else:
            keep = _select_in_bins(bin_id, low, fast, alloc, True)
            response = fast[keep]
        if keep.shape[0] == 0:
            return Features.empty("orb")

        # Step 5: orientation of the kept corners, level by level (keep is sorted by level).
        angle = np.empty(keep.shape[0], np.float32)
        bounds = np.searchsorted(level[keep], np.arange(len(pyramid) + 1), side="left")
        for lv in range(len(pyramid)):
            a, b = bounds[lv], bounds[lv + 1]
            if b > a:
                angle[a:b] = _ic_angle(pyramid[lv], np.ascontiguousarray(xy_all[keep[a:b]]), self._umax)
        return self._describe(gray, xy_all[keep], uv0[keep], level[keep], angle, response)

    def _orb_levels(self, gray: U8, n_levels: int) -> list[U8]:
        """OpenCV ORB's own pyramid of the image, smoothed for the descriptors.

        As ``cv2.ORB`` builds it: level l has size round(W / s_l) x round(H / s_l) with
        s_l = scale_factor**l in float32, resized (INTER_LINEAR_EXACT) from level l - 1;
        each level smoothed by a 7x7 Gaussian of sigma 2 (reflected border). With
        ``edge_margin`` below 18 (the pattern's reach) the tests read outside a level, where
        cv2 reads its reflected, unsmoothed border: the levels then get ``_pad`` px of it.
        """
        h, w = gray.shape
        levels = [gray]
        for lv in range(1, n_levels):
            s = np.float32(self.cfg.scale_factor**lv)
            size = (int(np.rint(np.float32(w) / s)), int(np.rint(np.float32(h) / s)))
            levels.append(cast(U8, cv2.resize(levels[-1], size, interpolation=cv2.INTER_LINEAR_EXACT)))
        blurred = [
            cv2.sepFilter2D(img, cv2.CV_8U, _BLUR_KERNEL, _BLUR_KERNEL, borderType=cv2.BORDER_REFLECT_101)
            for img in levels
        ]
        pad = self._pad
        if pad:
            for i, (img, b) in enumerate(zip(levels, blurred, strict=True)):
                ext = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
                ext[pad:-pad, pad:-pad] = b
                blurred[i] = ext
        return cast(list[U8], blurred)

    def _describe(
        self, gray: U8, xy: NDArray[np.int32], uv0: F64, level: I64, angle: F32, response: F32
    ) -> Features:
        """rBRIEF descriptors (the bits ``cv2.ORB.compute`` gives) of the selected corners,
        ``xy`` (n, 2) in their level's pixels, ordered by level."""
        sizes = (_ORB_PATCH_SIZE * self._scales[level]).astype(np.float32)
        n = xy.shape[0]
        desc = np.empty((n, ORB_DESCRIPTOR_BYTES), np.uint8)
        levels = self._orb_levels(gray, int(level[-1]) + 1)
        bounds = np.searchsorted(level, np.arange(len(levels) + 1), side="left")
        for lv, img in enumerate(levels):
            a, b = int(bounds[lv]), int(bounds[lv + 1])
            if b > a:
                _rbrief(img, np.ascontiguousarray(xy[a:b] + self._pad), angle[a:b], _PATTERN_X, _PATTERN_Y,
                        desc, a)
        return Features(
            uv=uv0.astype(np.float32),
            angle_deg=angle,
            response=response.astype(np.float32),
            octave=level.astype(np.int32),
            size=sizes,
            descriptors=desc,
            kind="orb",
        )


def extract_orb(gray: U8, cfg: OrbConfig | None = None, mask: U8 | None = None) -> Features:
    """Grid-distributed ORB features of a grey (H, W) uint8 image (paper 003 Eq. 3-5).

    Convenience wrapper building an :class:`OrbExtractor` per call; a tracker should keep
    one extractor and call :meth:`OrbExtractor.extract` per frame.
    """
    return OrbExtractor(cfg).extract(gray, mask)


# --------------------------------------------------------------------------- SIFT (thermal)


def _decode_sift_octave(packed: int) -> int:
    """OpenCV packs ``octave | layer << 8``; the octave byte is signed (-1 = upsampled)."""
    o = packed & 255
    return o - 256 if o >= 128 else o


def _sift_features(kps: Sequence[cv2.KeyPoint], desc: Any) -> Features:
    if desc is None or len(kps) == 0:
        return Features.empty("sift")
    n = len(kps)
    return Features(
        uv=np.asarray(cv2.KeyPoint.convert(kps), np.float32).reshape(n, 2),
        angle_deg=np.fromiter((k.angle for k in kps), np.float32, n),
        response=np.fromiter((k.response for k in kps), np.float32, n),
        octave=np.fromiter((_decode_sift_octave(k.octave) for k in kps), np.int32, n),
        size=np.fromiter((k.size for k in kps), np.float32, n),
        descriptors=np.ascontiguousarray(desc, dtype=np.float32),
        kind="sift",
    )


def extract_sift_adaptive(
    gray8: U8, cfg: SiftConfig | None = None, start_contrast: float | None = None
) -> tuple[Features, float]:
    """SIFT with an adaptive contrast threshold (paper 003 Sec. IV-C).

    Detect with the contrast threshold ``c`` (``start_contrast``, else
    ``cfg.initial_contrast``); while fewer than ``cfg.min_features`` keypoints are found
    and ``c`` is above ``cfg.min_contrast``, lower ``c`` by ``cfg.contrast_step`` (never
    below ``min_contrast``) and detect again. At most
    ``ceil((c0 - min_contrast) / step) + 1`` detections. Only the accepted keypoint set
    (the strongest ``max_features``) gets descriptors, computed once.

    ``start_contrast`` lets a tracker start from the previous frame's threshold; the
    loop only ever lowers it, as in the paper (a caller may reset it to the initial
    value now and then, e.g. at keyframes).

    Args:
        gray8: (H, W) uint8 image, e.g. from :func:`thermal_to_gray8`.
        cfg: loop parameters.
        start_contrast: first threshold to try, clipped to [min_contrast, initial_contrast].

    Returns:
        ``(features, contrast)``: SIFT features (kind ``"sift"``, float32 descriptors) and
        the contrast threshold that produced them.
    """
    cfg = cfg if cfg is not None else SiftConfig()
    if not isinstance(gray8, np.ndarray) or gray8.dtype != np.uint8 or gray8.ndim != 2:
        raise GeometryError(f"extract_sift_adaptive: expected a (H, W) uint8 image, got {gray8.shape}")
    c = cfg.initial_contrast if start_contrast is None else float(start_contrast)
    c = min(max(c, cfg.min_contrast), cfg.initial_contrast)
    sift = cv2.SIFT.create(
        nfeatures=cfg.max_features,
        nOctaveLayers=cfg.n_octave_layers,
        contrastThreshold=c,
        edgeThreshold=cfg.edge_threshold,
    )
    eps = 1e-9
    while True:
        sift.setContrastThreshold(c)
        kps = sift.detect(gray8, None)
        if len(kps) >= cfg.min_features or c <= cfg.min_contrast + eps:
            break
        c = max(round(c - cfg.contrast_step, 6), cfg.min_contrast)
    if len(kps) > cfg.max_features:  # nfeatures may keep ties beyond the limit
        kps = sorted(kps, key=lambda k: -k.response)[: cfg.max_features]
    if len(kps) == 0:
        return Features.empty("sift"), c
    kps_out, desc = sift.compute(gray8, list(kps))
    return _sift_features(kps_out, desc), c


def thermal_to_gray8(
    thermal_k: F32,
    *,
    low_percentile: float = 2.0,
    high_percentile: float = 95.0,
    clahe_clip: float | None = 3.0,
    clahe_tiles: tuple[int, int] = (8, 8),
) -> U8:
    """8-bit image of a thermal frame for feature detection.

    Robust contrast stretch: the ``low_percentile``..``high_percentile`` range of the
    finite temperatures maps to 0..255 (clipped), then optional CLAHE (contrast-limited
    adaptive histogram equalisation; ``clahe_clip=None`` turns it off).

    Args:
        thermal_k: (h, w) float temperatures in kelvin; NaN / inf pixels become 0.

    Returns:
        (h, w) uint8. A uniform (or all non-finite) frame gives all zeros.
    """
    t = np.asarray(thermal_k, dtype=np.float32)
    if t.ndim != 2:
        raise GeometryError(f"thermal_to_gray8: expected (h, w), got {t.shape}")
    finite = np.isfinite(t)
    vals = t[finite]
    if vals.size == 0:
        return np.zeros(t.shape, np.uint8)
    # Percentiles from a subsample keep this well under a millisecond on 388x284.
    step = max(1, vals.size // 20000)
    lo, hi = np.percentile(vals[::step], [low_percentile, high_percentile])
    if not hi - lo > 1e-6:
        return np.zeros(t.shape, np.uint8)
    scaled = (np.where(finite, t, lo) - lo) * (255.0 / (hi - lo))
    out = np.clip(scaled, 0.0, 255.0).astype(np.uint8)
    if clahe_clip is not None:
        out = cv2.createCLAHE(clipLimit=clahe_clip, tileGridSize=clahe_tiles).apply(out)
    return out


# --------------------------------------------------------------------------- matching


class Matches(NamedTuple):
    """Index pairs (K,) int64 into query and train sets, and their descriptor distance (K,)."""

    query_idx: I64
    train_idx: I64
    distance: F32


def _empty_matches() -> Matches:
    return Matches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))


def match_descriptors(
    query: NDArray[np.uint8] | NDArray[np.float32],
    train: NDArray[np.uint8] | NDArray[np.float32],
    *,
    ratio: float | None = 0.8,
    cross_check: bool = False,
    max_distance: float | None = None,
) -> Matches:
    """Brute-force descriptor matching with Lowe's ratio test.

    The norm follows the dtype: uint8 (ORB, (N, 32)) -> Hamming, float32 (SIFT,
    (N, 128)) -> L2. A query is matched to its nearest train descriptor if
    ``d1 < ratio * d2`` (second nearest; skipped when ``ratio`` is None or train has
    one row) and ``d1 <= max_distance`` (if given). With ``cross_check`` the query must
    also be the nearest of its train descriptor, which makes the result one-to-one;
    without it two queries may share a train index.

    Returns:
        :class:`Matches`, ordered by query index.
    """
    q = cast(NDArray[np.uint8] | NDArray[np.float32], np.asarray(query))
    t = cast(NDArray[np.uint8] | NDArray[np.float32], np.asarray(train))
    if q.ndim != 2 or t.ndim != 2 or q.shape[1] != t.shape[1] or q.dtype != t.dtype:
        raise GeometryError(
            f"match_descriptors: need two (N, D) arrays of one dtype, got {q.shape} {q.dtype}, "
            f"{t.shape} {t.dtype}"
        )
    if q.dtype == np.uint8:
        norm = cv2.NORM_HAMMING
    elif q.dtype == np.float32:
        norm = cv2.NORM_L2
    else:
        raise GeometryError(f"match_descriptors: dtype must be uint8 or float32, got {q.dtype}")
    if q.shape[0] == 0 or t.shape[0] == 0:
        return _empty_matches()
    matcher = cv2.BFMatcher(norm, crossCheck=False)
    k = 2 if ratio is not None and t.shape[0] >= 2 else 1
    knn = matcher.knnMatch(q, t, k=k)
    qi: list[int] = []
    ti: list[int] = []
    dist: list[float] = []
    for pair in knn:
        if not pair:
            continue
        best = pair[0]
        if k == 2 and len(pair) == 2 and ratio is not None and not best.distance < ratio * pair[1].distance:
            continue
        if max_distance is not None and best.distance > max_distance:
            continue
        qi.append(best.queryIdx)
        ti.append(best.trainIdx)
        dist.append(best.distance)
    out = Matches(np.asarray(qi, np.int64), np.asarray(ti, np.int64), np.asarray(dist, np.float32))
    if cross_check and out.query_idx.size:
        back = matcher.match(t, q)
        best_query_of_train = np.full(t.shape[0], -1, np.int64)
        for mt in back:
            best_query_of_train[mt.queryIdx] = mt.trainIdx
        mutual = best_query_of_train[out.train_idx] == out.query_idx
        out = Matches(out.query_idx[mutual], out.train_idx[mutual], out.distance[mutual])
    return out


@njit(cache=True, nogil=True)
def _match_projected_kernel(
    map_desc: NDArray[np.uint64],
    map_uv: F64,
    radius: F64,
    map_oct: NDArray[np.int64],
    oct_window: int,
    frame_desc: NDArray[np.uint64],
    frame_uv: F64,
    frame_oct: NDArray[np.int64],
    cell: float,
    max_hamming: int,
    ratio: float,
) -> tuple[I64, I64]:
    """Best frame feature within ``radius`` of each map point, ratio test, then one-to-one."""
    n = frame_uv.shape[0]
    m = map_uv.shape[0]
    u_min = frame_uv[0, 0]
    v_min = frame_uv[0, 1]
    u_max = u_min
    v_max = v_min
    for j in range(n):
        u_min = min(u_min, frame_uv[j, 0])
        u_max = max(u_max, frame_uv[j, 0])
        v_min = min(v_min, frame_uv[j, 1])
        v_max = max(v_max, frame_uv[j, 1])
    n_cols = int((u_max - u_min) / cell) + 1
    n_rows = int((v_max - v_min) / cell) + 1
    # Bucket the frame features (counting sort by cell): features of cell c are
    # order[start[c]:start[c + 1]].
    cell_of = np.empty(n, np.int64)
    start = np.zeros(n_cols * n_rows + 1, np.int64)
    for j in range(n):
        c = int((frame_uv[j, 1] - v_min) / cell) * n_cols + int((frame_uv[j, 0] - u_min) / cell)
        cell_of[j] = c
        start[c + 1] += 1
    for c in range(n_cols * n_rows):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for j in range(n):
        order[fill[cell_of[j]]] = j
        fill[cell_of[j]] += 1

    words = map_desc.shape[1]
    best_j = np.full(m, -1, np.int64)
    best_d = np.full(m, 1 << 30, np.int64)
    for i in range(m):
        u = map_uv[i, 0]
        v = map_uv[i, 1]
        r = radius[i]
        if not (np.isfinite(u) and np.isfinite(v) and r >= 0.0):
            continue
        c0 = max(math.floor((u - r - u_min) / cell), 0)
        c1 = min(math.floor((u + r - u_min) / cell), n_cols - 1)
        r0 = max(math.floor((v - r - v_min) / cell), 0)
        r1 = min(math.floor((v + r - v_min) / cell), n_rows - 1)
        d1 = 1 << 30
        d2 = 1 << 30
        j1 = -1
        r2 = r * r
        for row in range(r0, r1 + 1):
            for col in range(c0, c1 + 1):
                c = row * n_cols + col
                for k in range(start[c], start[c + 1]):
                    j = order[k]
                    du = frame_uv[j, 0] - u
                    dv = frame_uv[j, 1] - v
                    if du * du + dv * dv > r2:
                        continue
                    if oct_window >= 0 and abs(frame_oct[j] - map_oct[i]) > oct_window:
                        continue
                    d = 0
                    for w in range(words):
                        d += popcount64(map_desc[i, w] ^ frame_desc[j, w])
                    if d < d1:
                        d2 = d1
                        d1 = d
                        j1 = j
                    elif d < d2:
                        d2 = d
        if j1 < 0 or d1 > max_hamming:
            continue
        if d2 < (1 << 30) and d1 > ratio * d2:
            continue
        best_j[i] = j1
        best_d[i] = d1

    # One-to-one: the closest descriptor wins a contested frame feature (ties: lower map index).
    cand = np.nonzero(best_j >= 0)[0]
    by_dist = cand[np.argsort(best_d[cand], kind="mergesort")]
    taken = np.zeros(n, np.bool_)
    out_i = np.empty(by_dist.shape[0], np.int64)
    out_j = np.empty(by_dist.shape[0], np.int64)
    k_out = 0
    for i in by_dist:
        j = best_j[i]
        if taken[j]:
            continue
        taken[j] = True
        out_i[k_out] = i
        out_j[k_out] = j
        k_out += 1
    sel = np.argsort(out_i[:k_out])
    return out_i[:k_out][sel], out_j[:k_out][sel]


def match_projected(
    map_desc: NDArray[np.uint8],
    map_uv_pred: F64 | F32,
    frame: Features,
    radius_px: float | F64,
    max_hamming: int = 50,
    ratio: float = 0.9,
    *,
    map_octave_pred: NDArray[np.integer] | None = None,
    octave_window: int = 1,
) -> tuple[I64, I64]:
    """Guided matching of projected map points to frame ORB features.

    For each map point i, the frame features within ``radius_px`` (Euclidean, pixels)
    of its predicted position are searched for the smallest Hamming distance d1; the
    match is kept if ``d1 <= max_hamming`` and ``d1 <= ratio * d2`` (d2: second best in
    the window, if any). Conflicts (two map points on one feature) go to the smaller
    distance, so the result is one-to-one; the loser is dropped, not re-matched.

    Args:
        map_desc: (M, 32) uint8 rBRIEF descriptors of the map points.
        map_uv_pred: (M, 2) predicted pixel positions in the distorted image (e.g.
            ``PinholeCamera.project`` of the points in the camera frame); rows with NaN
            (not visible) are skipped.
        frame: the frame's ORB features.
        radius_px: search radius in pixels, one value or (M,) per map point (e.g.
            scaled by the predicted pyramid level).
        max_hamming: largest accepted Hamming distance (bits of 256).
        ratio: Lowe ratio between best and second-best distance.
        map_octave_pred: optional (M,) predicted pyramid level; only frame features whose
            octave is within ``octave_window`` of it are considered.

    Returns:
        ``(map_idx, frame_idx)``: (K,) int64 each, sorted by map index, one-to-one.
    """
    desc = np.asarray(map_desc)
    uv = np.asarray(map_uv_pred, dtype=np.float64)
    m = desc.shape[0]
    if desc.ndim != 2 or desc.shape[1] != ORB_DESCRIPTOR_BYTES or desc.dtype != np.uint8:
        raise GeometryError(f"match_projected: map_desc must be (M, 32) uint8, got {desc.shape} {desc.dtype}")
    if uv.shape != (m, 2):
        raise GeometryError(f"match_projected: map_uv_pred must be ({m}, 2), got {uv.shape}")
    if frame.kind != "orb":
        raise GeometryError(f"match_projected: frame features must be ORB, got {frame.kind}")
    radius = np.broadcast_to(np.asarray(radius_px, dtype=np.float64), (m,)).copy()
    if map_octave_pred is None:
        map_oct = np.zeros(m, np.int64)
        window = -1
    else:
        map_oct = np.asarray(map_octave_pred, dtype=np.int64).reshape(-1)
        if map_oct.shape != (m,):
            raise GeometryError(f"match_projected: map_octave_pred must be ({m},), got {map_oct.shape}")
        window = int(octave_window)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    finite_r = radius[np.isfinite(radius)]
    if m == 0 or len(frame) == 0 or finite_r.size == 0:
        return empty
    # Bucket side: the largest radius, so a search touches at most 3x3 buckets; at most
    # ~1e6 buckets whatever the spread of the frame's keypoints.
    extent = float(np.ptp(frame.uv, axis=0).max()) if len(frame) > 1 else 0.0
    cell = max(float(finite_r.max()), 4.0, extent / 1000.0)
    radius = np.where(np.isfinite(radius), radius, -1.0)
    return _match_projected_kernel(
        np.ascontiguousarray(desc).view(np.uint64),
        uv,
        radius,
        map_oct,
        window,
        np.ascontiguousarray(frame.descriptors).view(np.uint64),
        frame.uv.astype(np.float64),
        frame.octave.astype(np.int64),
        cell,
        int(max_hamming),
        float(ratio),
    )


__all__ = [
    "ORB_DESCRIPTOR_BYTES",
    "SIFT_DESCRIPTOR_LEN",
    "FeatureKind",
    "Features",
    "Matches",
    "OrbConfig",
    "OrbExtractor",
    "SiftConfig",
    "extract_orb",
    "extract_sift_adaptive",
    "match_descriptors",
    "match_projected",
    "thermal_to_gray8",
]
