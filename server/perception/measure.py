"""3D object measurements from instance masks and depth (paper 000 Eq. 1).

Paper 000 models an object observation as ``(class, pose, size)`` plus appearance; this
module measures them for each :class:`Instance` of one keyframe:

1. erode the mask (mixed depth at object borders), back-project the valid depth inside
   it with the pinhole model;
2. remove outliers: split the sorted depths into layers at gaps wider than
   ``max(depth_gap_m, depth_gap_relative * depth)`` and keep the layer holding the median
   depth (background seen through or beside the object, occluders in front), then
   radius outlier removal (isolated points: fewer than ``radius_min_neighbours`` within
   ``radius_m``). Layers rather than a band around the median depth, and neighbour
   counts rather than distance statistics, because real surfaces seen at grazing angles
   span much depth and are sparse (a box top seen from the side). Optionally
   (``cluster_gap_m``) keep only the largest 3D piece, for leaky detector masks;
3. pose, gravity-aligned (object z = world up = ``-gravity_world``): yaw from the
   dominant vertical plane (RANSAC on the points projected on the ground, a line there
   is a plane with a horizontal normal) when it holds at least ``plane_min_fraction``
   of the points, else from PCA of the projected points; centre = centre of the
   bounding box in that frame; size = its extent;
4. appearance: HSV histogram (L1-normalised) and ORB descriptors inside the mask.

Object frame (as the simulator's ``objects.json``): origin at the box centre, z up, x
"forward". A box's yaw is ambiguous by 180 deg (and by 90 deg when its footprint is
square), and a single view cannot tell an object's front, so the measurement chooses x
along the longer horizontal extent and the yaw in [-90, 90) deg. Consumers comparing
with ground truth must compare modulo this symmetry (``bench/perception.py``).

Only the visible surface is measured: the box of a partly seen object is smaller than
the object and its centre moves towards the camera. Doors cut by the left or right image
border are the exception: their box is widened to the usual door width beyond that border
(``MeasureConfig.clipped_width_m``); ``points_camera`` still holds the visible points only.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final, Literal, NamedTuple, get_args

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from wardmap.server.perception.masks import clipped_side, densest_window, principal_direction, ring_around
from wardmap.server.perception.types import CLASS_SIZE_M, Instance, ObjectMeasurement
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.se3 import check_transform, inverse, yaw_rotation

__all__ = [
    "SKIP_KINDS",
    "MeasureConfig",
    "MeasureReport",
    "Skip",
    "SkipKind",
    "mean_rgb",
    "measure_instances",
    "measure_instances_report",
]

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

_RANSAC_SCORE_POINTS = 800
"""Points each RANSAC hypothesis is scored on (a seeded random subset)."""
_ORB_MARGIN_PX = 32
"""Image kept around a mask for ORB: its 31 px patch and edge threshold need context."""
_STATIC_BOUNDED = ("door", "cabinet", "bed", "desk", "sink", "wall_monitor")
"""Classes whose measured width is bounded by default (``MeasureConfig.max_width_m``)."""
_TIGHTER_BOUND_M = {"door": 1.25}
"""Measurement bounds tighter than the association's ``CLASS_SIZE_M`` (``MeasureConfig.max_width_m``)."""


@dataclass(frozen=True)
class MeasureConfig:
    """Parameters of :func:`measure_instances` (all lengths in metres)."""

    min_depth_m: float = 0.2
    """Depth below this is ignored (sensor minimum range)."""
    max_depth_m: float = 8.0
    """Depth beyond this is ignored (noise grows with depth squared)."""
    erode_px: int = 1
    """Mask erosion radius in pixels before back-projection (mixed depth at borders)."""
    min_points: int = 50
    """Instances with fewer inlier points are skipped."""
    min_depth_fraction: float = 0.25
    """Instances whose mask has valid depth on a smaller share of its pixels are skipped: the
    3D points then come from whatever part returns depth (a monitor's bezel and stand when the
    black screen returns none), not from the object."""
    max_points: int = 3000
    """Points are subsampled (fixed stride) to at most this many before outlier removal."""
    depth_gap_m: float = 0.2
    """Depth layers: sorted depths split where consecutive values differ by more than this."""
    depth_gap_relative: float = 0.05
    """... or by more than this fraction of the depth, when larger (noise grows with depth)."""
    radius_m: float = 0.05
    """Radius outlier removal: neighbourhood radius of each point."""
    radius_min_neighbours: int = 4
    """Radius outlier removal: fewest other points inside the radius (0 disables)."""
    cluster_gap_m: float = 0.0
    """Keep only the largest 3D piece of the points, pieces being separated by gaps wider
    than this (Euclidean clustering); 0 disables."""
    extent_quantile: float = 0.0
    """The box spans this quantile to ``1 - extent_quantile`` of the points along each axis
    (0 = min/max); a few surviving outliers then cannot stretch it."""
    max_width_m: tuple[tuple[str, float], ...] = tuple(
        (name, _TIGHTER_BOUND_M.get(name, horizontal))
        for name, horizontal, _ in CLASS_SIZE_M if name in _STATIC_BOUNDED
    )
    """``[class, width]`` pairs: the widest an object of the class can be, metres (the static
    classes' horizontal bounds in ``types.CLASS_SIZE_M``, but doors 1.25 m rather than 1.3 m,
    so that a spill in a 1.16 m door's box is at most 9 cm and its centre at most 4.5 cm off).
    When the points of an instance of the class span more than that along the box's x axis,
    only the points inside the ``width``-wide window holding the most of them are kept
    (:func:`densest_window`) and the box is fitted to those; its centre can still lie up to
    half the slack (bound minus the true width) towards the extra points. The network's door
    mask runs onto the flush wall beside the door at grazing views, and a few hundred wall
    pixels would stretch the box along the wall."""
    clipped_width_m: tuple[tuple[str, float], ...] = (("door", 1.2),)
    """``[class, width]`` pairs: the usual width of an object of the class, metres. An instance
    of the class whose mask reaches the left or the right image border (not both) and whose box
    is narrower than that is taken to continue beyond the border: its box is widened to
    ``width`` along its x axis on the side of the border, and its centre moves by half the
    difference (:func:`_widen_at_border`); otherwise a door cut by the border is measured at
    its visible part's centre, off along the wall. A door leaf and frame are 1.1-1.25 m wide in
    hospitals (1.16 m in the simulator). ``[]`` turns it off; set it to your building's doors."""
    plane_threshold_m: float = 0.02
    """RANSAC: distance of an inlier to the vertical plane."""
    plane_min_fraction: float = 0.3
    """RANSAC: the plane fixes the yaw if it explains at least this fraction of points."""
    plane_iterations: int = 200
    """RANSAC iterations (seeded: the result is deterministic)."""
    hist_bins: tuple[int, int, int] = (16, 4, 4)
    """HSV histogram bins (hue, saturation, value); length of ``color_hist`` is their product."""
    orb_features: int = 200
    """Most ORB keypoints per instance."""
    raised_classes: tuple[str, ...] = ("wall_monitor", "sink")
    """Classes that stand out from the wall they hang on. Their instances are skipped when the
    mask lies flush with its surroundings (see ``flush_tolerance_m``): a poster taken for a
    monitor, a patch of tiled wall taken for a sink."""
    flush_tolerance_m: float = 0.02
    """Flush: the median depth of the mask is within this of the median depth of a ring
    around it (``flush_ring_px`` wide, 2 px away from the mask); 0 disables the test. A
    monitor's screen stands 5 cm or more proud of the wall, a poster 1 cm."""
    flush_ring_px: int = 10
    """Width of that ring, pixels."""
    seed: int = 0
    """Seed of the RANSAC sampler."""

    def __post_init__(self) -> None:
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError("MeasureConfig: need 0 < min_depth_m < max_depth_m")
        if not 0.0 <= self.min_depth_fraction <= 1.0:
            raise ConfigError(
                f"MeasureConfig: min_depth_fraction must lie in 0..1, got {self.min_depth_fraction}"
            )
        if self.erode_px < 0 or self.min_points < 3 or self.max_points < self.min_points:
            raise ConfigError("MeasureConfig: need erode_px >= 0, min_points >= 3, max_points >= min_points")
        if self.depth_gap_m <= 0 or self.depth_gap_relative < 0:
            raise ConfigError("MeasureConfig: need depth_gap_m > 0 and depth_gap_relative >= 0")
        if self.cluster_gap_m < 0:
            raise ConfigError("MeasureConfig: need cluster_gap_m >= 0")
        if self.radius_m <= 0 or self.radius_min_neighbours < 0:
            raise ConfigError("MeasureConfig: need radius_m > 0 and radius_min_neighbours >= 0")
        if not 0 <= self.extent_quantile < 0.5:
            raise ConfigError("MeasureConfig: need 0 <= extent_quantile < 0.5")
        for key in ("max_width_m", "clipped_width_m"):
            for name, width in getattr(self, key):
                if not width > 0:
                    raise ConfigError(f"MeasureConfig: {key} of {name!r} must be > 0, got {width}")
        if self.plane_threshold_m <= 0 or not 0 < self.plane_min_fraction <= 1 or self.plane_iterations < 1:
            raise ConfigError("MeasureConfig: need plane_threshold_m > 0, 0 < plane_min_fraction <= 1 "
                              "and plane_iterations >= 1")
        if self.flush_tolerance_m < 0 or self.flush_ring_px < 1:
            raise ConfigError("MeasureConfig: need flush_tolerance_m >= 0 and flush_ring_px >= 1")
        if len(self.hist_bins) != 3 or min(self.hist_bins) < 1 or self.orb_features < 0:
            raise ConfigError("MeasureConfig: hist_bins needs three positive counts; orb_features >= 0")


SkipKind = Literal["empty_mask", "little_depth", "flush", "few_points"]
SKIP_KINDS: Final[tuple[SkipKind, ...]] = get_args(SkipKind)
"""Why an instance is not measured: an empty mask; valid depth on less than
``min_depth_fraction`` of the mask; a raised class flush with its surroundings; fewer than
``min_points`` points left after outlier removal."""


class Skip(NamedTuple):
    """An instance :func:`measure_instances_report` did not measure."""

    instance: int
    """Its index in the input instances."""
    kind: SkipKind
    """Why (a metric label)."""
    reason: str
    """The same for a person, with the numbers."""


@dataclass(frozen=True)
class MeasureReport:
    """Result of :func:`measure_instances_report`.

    Attributes:
        measurements: one per measured instance, in input order.
        skipped: a :class:`Skip` for each instance not measured, in input order.
    """

    measurements: list[ObjectMeasurement]
    skipped: list[Skip] = field(default_factory=list)


def _gravity_rotation(gravity_world: ArrayLike) -> F64:
    """R_world_gravity (3, 3): a frame whose z is ``-gravity_world`` (world up)."""
    g = np.asarray(gravity_world, dtype=np.float64).reshape(-1)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-9:
        raise GeometryError(f"gravity_world must be a finite non-zero (3,) vector, got {g}")
    z = -g / np.linalg.norm(g)
    # x: world x made horizontal (world y if x is vertical), so z = up keeps world yaw.
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - z * (ref @ z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _back_project(mask: NDArray[np.bool_], depth_m: F32, origin: tuple[int, int], camera: PinholeCamera,
                  cfg: MeasureConfig) -> F64:
    """Camera-frame points (N, 3) of the valid depth under ``mask``, in the median's depth layer.

    ``mask`` and ``depth_m`` are a window of the image whose top-left pixel is ``origin`` (row, col).
    """
    rows, cols = np.nonzero(mask)
    z = depth_m[rows, cols].astype(np.float64)
    rows, cols = rows + origin[0], cols + origin[1]
    ok = np.isfinite(z) & (z >= cfg.min_depth_m) & (z <= cfg.max_depth_m)
    rows, cols, z = rows[ok], cols[ok], z[ok]
    if z.size == 0:
        return np.zeros((0, 3))
    if z.size > cfg.max_points:
        step = math.ceil(z.size / cfg.max_points)
        rows, cols, z = rows[::step], cols[::step], z[::step]
    # Depth gaps wider than the jump threshold split the mask's depths into layers (object,
    # background bleeding through, foreground occluders); keep the layer holding the median.
    order = np.argsort(z, kind="stable")
    zs = z[order]
    gaps = np.flatnonzero(np.diff(zs) > np.maximum(cfg.depth_gap_m, cfg.depth_gap_relative * zs[1:]))
    median_at = zs.size // 2
    lo_i = int(gaps[gaps < median_at][-1]) + 1 if np.any(gaps < median_at) else 0
    hi_i = int(gaps[gaps >= median_at][0]) + 1 if np.any(gaps >= median_at) else zs.size
    keep = np.zeros(z.size, dtype=bool)
    keep[order[lo_i:hi_i]] = True
    uv = np.column_stack([cols[keep], rows[keep]]).astype(np.float64)
    return camera.unproject(uv, z[keep])


def _radius_inliers(points: F64, cfg: MeasureConfig) -> NDArray[np.bool_]:
    """Mask (N,) of points with at least ``radius_min_neighbours`` others within ``radius_m``."""
    if cfg.radius_min_neighbours == 0 or points.shape[0] == 0:
        return np.ones(points.shape[0], dtype=bool)
    k = cfg.radius_min_neighbours + 1  # the point itself is its own nearest neighbour
    if points.shape[0] < k:
        return np.zeros(points.shape[0], dtype=bool)
    dist, _ = cKDTree(points).query(points, k=[k], distance_upper_bound=cfg.radius_m)
    return np.asarray(np.isfinite(dist[:, 0]))


def _largest_cluster(points: F64, gap_m: float) -> NDArray[np.bool_]:
    """Mask (N,) of the largest 3D piece of ``points`` (N, 3).

    Euclidean clustering on a voxel grid of side ``gap_m``: occupied voxels that touch
    (26-neighbourhood) form one piece, so pieces are separated by gaps of at least
    ``gap_m``; the piece with the most points wins.
    """
    n = points.shape[0]
    if n == 0:
        return np.ones(0, dtype=bool)
    keys = np.floor((points - points.min(axis=0)) / gap_m).astype(np.int64)
    voxels, of_point = np.unique(keys, axis=0, return_inverse=True)
    of_point = of_point.reshape(-1)
    m = voxels.shape[0]
    dims = voxels.max(axis=0) + 3
    code = ((voxels[:, 0] + 1) * dims[1] + voxels[:, 1] + 1) * dims[2] + voxels[:, 2] + 1
    order = np.argsort(code)
    sorted_code = code[order]
    rows, cols = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                if (dx, dy, dz) <= (0, 0, 0):
                    continue  # each neighbour pair once
                target = code + (dx * dims[1] + dy) * dims[2] + dz
                at = np.minimum(np.searchsorted(sorted_code, target), m - 1)
                hit = sorted_code[at] == target
                rows.append(np.flatnonzero(hit))
                cols.append(order[at[hit]])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, np.int8), (r, c)), shape=(m, m))
    _, voxel_label = connected_components(graph, directed=False)
    label = voxel_label[of_point]
    return np.asarray(label == np.bincount(label).argmax())


def _ransac_line_direction(xy: F64, cfg: MeasureConfig) -> F64 | None:
    """Unit direction (2,) of the dominant line in ground-plane points (N, 2), or None.

    A line on the ground plane is a vertical plane in 3D (normal horizontal); it fixes the
    yaw when its inliers are at least ``plane_min_fraction`` of the points. The direction
    is refined by PCA of the inliers.
    """
    n = xy.shape[0]
    rng = np.random.default_rng(cfg.seed)
    # Hypotheses are scored on at most _RANSAC_SCORE_POINTS points, all at once.
    score_pts = xy if n <= _RANSAC_SCORE_POINTS else xy[rng.choice(n, _RANSAC_SCORE_POINTS, replace=False)]
    pairs = rng.integers(0, n, size=(cfg.plane_iterations, 2))
    d = xy[pairs[:, 1]] - xy[pairs[:, 0]]
    length = np.hypot(d[:, 0], d[:, 1])
    ok = length > 1e-3
    if not ok.any():
        return None
    normals = np.column_stack([-d[ok, 1], d[ok, 0]]) / length[ok, None]  # (M, 2)
    offsets = np.sum(normals * xy[pairs[ok, 0]], axis=1)  # (M,)
    counts = (np.abs(score_pts @ normals.T - offsets) <= cfg.plane_threshold_m).sum(axis=0)
    best = int(np.argmax(counts))
    if counts[best] < cfg.plane_min_fraction * score_pts.shape[0]:
        return None
    inliers = np.abs(xy @ normals[best] - offsets[best]) <= cfg.plane_threshold_m
    return principal_direction(xy[inliers])


def _gravity_box(points_g: F64, cfg: MeasureConfig) -> tuple[float, F64, F64, str]:
    """Yaw, centre (3,), size (3,) of the gravity-aligned box of points (N, 3) (z up).

    Returns the yaw of object x about z in radians in [-pi/2, pi/2) with x along the
    longer horizontal extent, the box centre and size in the points' frame, and the yaw
    source ("plane" or "pca").
    """
    xy = points_g[:, :2]
    direction = _ransac_line_direction(xy, cfg)
    source = "plane"
    if direction is None:
        direction, source = principal_direction(xy), "pca"
    yaw = math.atan2(direction[1], direction[0])
    q = cfg.extent_quantile
    for _ in range(2):
        R = yaw_rotation(yaw)[:2, :2]
        local = xy @ R  # coordinates along the object x, y axes
        ext = np.ptp(local, axis=0)
        if ext[0] >= ext[1]:
            break
        yaw += math.pi / 2
    yaw = (yaw + math.pi / 2) % math.pi - math.pi / 2
    R = yaw_rotation(yaw)[:2, :2]
    local = np.column_stack([xy @ R, points_g[:, 2]])
    lo, hi = np.quantile(local, [q, 1.0 - q], axis=0)
    centre_xy = R @ ((lo[:2] + hi[:2]) / 2)
    size = hi - lo
    return yaw, np.array([centre_xy[0], centre_xy[1], (lo[2] + hi[2]) / 2]), size, source


def _widen_at_border(centre_g: F64, size: F64, yaw: float, width: float, mask: NDArray[np.bool_],
                     T_gc: F64, camera: PinholeCamera) -> tuple[F64, F64]:
    """Centre (3,) and size (3,) of a box widened to ``width`` beyond the image border.

    When ``mask`` (H, W) reaches exactly one of the left and right image borders, the object
    continues out of view there: the box (gravity frame: centre ``centre_g``, ``size``, x axis
    at ``yaw``) grows along its x axis to ``width`` metres on the side of its end that projects
    nearer that border, so the centre moves by ``(width - size[0]) / 2``. Otherwise (no border,
    both borders, an end behind the camera) the box is returned unchanged. ``T_gc`` (4, 4) maps
    camera to gravity frame.
    """
    side = clipped_side(mask)
    if not side:
        return centre_g, size
    axis = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    ends_g = centre_g + np.outer([1.0, -1.0], axis * size[0] / 2)  # (2, 3): +x end, -x end
    ends_c = (ends_g - T_gc[:3, 3]) @ T_gc[:3, :3]  # gravity -> camera: R^T (p - t)
    uv, in_front = camera.project(ends_c)
    if not in_front.all():
        return centre_g, size
    u = uv[:, 0]
    toward = 1.0 if (u[0] < u[1]) == (side < 0) else -1.0  # sign of x towards the clipped end
    widened = size.copy()
    widened[0] = width
    return centre_g + toward * axis * (width - size[0]) / 2, widened


def mean_rgb(
    histograms: Sequence[ArrayLike], bins: tuple[int, int, int]
) -> tuple[float, float, float] | None:
    """Mean colour (R, G, B in 0..255) of the pixels behind HSV histograms made by
    :func:`measure_instances` with ``bins`` (``MeasureConfig.hist_bins``).

    Each histogram is L1-normalised, so every measurement weighs the same. The colour is the
    average of the bins' centre colours weighted by the summed histogram (the least saturated
    bin counts as grey): coarse (with the default 16 x 4 x 4 bins, one value bin spans 64
    grey levels) but enough to tell a red chair from a blue one. None when there is no
    histogram, one has another length, or all are empty.
    """
    k = bins[0] * bins[1] * bins[2]
    hists = [np.asarray(h, dtype=np.float64).ravel() for h in histograms]
    if not hists or any(h.size != k for h in hists):
        return None
    total = np.sum(hists, axis=0)
    if not total.sum() > 0:
        return None
    h, s, v = np.meshgrid(*[(np.arange(n) + 0.5) * (top / n) for n, top in zip(bins, (180, 256, 256),
                                                                                  strict=True)],
                          indexing="ij")
    s[:, 0, :] = 0.0  # the least saturated bin holds the greys (walls, metal): no tint
    hsv = np.stack([h, s, v], axis=-1).reshape(1, k, 3).astype(np.float32)
    hsv[..., 0] *= 2.0  # float HSV in OpenCV: hue in degrees, saturation and value in 0..1
    hsv[..., 1:] /= 255.0
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB).reshape(k, 3).astype(np.float64) * 255.0
    out = total @ rgb / total.sum()
    return (float(out[0]), float(out[1]), float(out[2]))


def _appearance(
    bgr: NDArray[np.uint8], mask: NDArray[np.bool_], cfg: MeasureConfig
) -> tuple[F32, NDArray[np.uint8]]:
    """HSV histogram (K,) L1-normalised and ORB descriptors (M, 32) inside ``mask``.

    Both are computed on the mask's bounding box plus an ORB border margin, not the
    whole image (same result, a fraction of the time).
    """
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    margin = _ORB_MARGIN_PX
    r0, r1 = max(0, rows[0] - margin), min(mask.shape[0], rows[-1] + 1 + margin)
    c0, c1 = max(0, cols[0] - margin), min(mask.shape[1], cols[-1] + 1 + margin)
    bgr = bgr[r0:r1, c0:c1]
    mask_u8 = mask[r0:r1, c0:c1].astype(np.uint8) * 255
    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
    h_bins, s_bins, v_bins = cfg.hist_bins
    hist = cv2.calcHist([hsv], [0, 1, 2], mask_u8, [h_bins, s_bins, v_bins], [0, 180, 0, 256, 0, 256])
    counts: F32 = np.asarray(hist, dtype=np.float32).ravel()
    total = float(counts.sum())
    if total > 0:
        counts = counts / np.float32(total)
    descriptors: NDArray[np.uint8] = np.zeros((0, 32), np.uint8)
    if cfg.orb_features > 0:
        gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        orb = cv2.ORB.create(nfeatures=cfg.orb_features)
        _, desc = orb.detectAndCompute(gray, mask_u8)
        if desc is not None:
            descriptors = np.ascontiguousarray(desc, dtype=np.uint8)
    return counts, descriptors


def measure_instances_report(
    instances: Sequence[Instance],
    *,
    bgr: NDArray[np.uint8],
    depth_m: NDArray[np.float32],
    camera: PinholeCamera,
    T_world_camera: ArrayLike,
    keyframe: str,
    stamp: float,
    config: MeasureConfig | None = None,
    gravity_world: ArrayLike = (0.0, 0.0, -1.0),
) -> MeasureReport:
    """Measure every instance of one keyframe; see :func:`measure_instances` for the arguments.

    Returns:
        A :class:`MeasureReport` with the measurements and, for each instance not measured,
        a :class:`Skip` (its index, kind from :data:`SKIP_KINDS`, reason).
    """
    cfg = config or MeasureConfig()
    image = np.asarray(bgr)
    depth = np.asarray(depth_m)
    shape = (camera.height, camera.width)
    if image.dtype != np.uint8 or image.shape != (*shape, 3):
        raise GeometryError(
            f"measure_instances: expected a uint8 {(*shape, 3)} BGR image, got {image.dtype} {image.shape}"
        )
    if depth.shape != shape:
        raise GeometryError(f"measure_instances: expected depth {shape}, got {depth.shape}")
    depth = depth.astype(np.float32, copy=False)
    T_wc = check_transform(T_world_camera, "T_world_camera")
    T_cw = inverse(T_wc)
    R_wg = _gravity_rotation(gravity_world)
    T_gc = np.eye(4)
    T_gc[:3, :3] = R_wg.T @ T_wc[:3, :3]
    T_gc[:3, 3] = R_wg.T @ T_wc[:3, 3]
    kernel = None
    if cfg.erode_px > 0:
        side = 2 * cfg.erode_px + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side))
    report = MeasureReport([], [])
    max_width = dict(cfg.max_width_m)
    clipped_width = dict(cfg.clipped_width_m)
    for index, inst in enumerate(instances):
        if inst.mask.shape != shape:
            raise GeometryError(
                f"measure_instances: instance {index} mask {inst.mask.shape} != image {shape}"
            )
        rows = np.flatnonzero(inst.mask.any(axis=1))
        cols = np.flatnonzero(inst.mask.any(axis=0))
        if rows.size == 0:
            report.skipped.append(Skip(index, "empty_mask", "empty mask: 0 points < min_points"))
            log.debug("measure %s: skip instance %d (%s): empty mask", keyframe, index, inst.category)
            continue
        # Work in the mask's bounding window (plus the erosion margin), not the whole image.
        pad = cfg.erode_px + 1
        r0, r1 = max(0, rows[0] - pad), min(shape[0], rows[-1] + 1 + pad)
        c0, c1 = max(0, cols[0] - pad), min(shape[1], cols[-1] + 1 + pad)
        mask = inst.mask[r0:r1, c0:c1]
        if cfg.min_depth_fraction > 0:
            d = depth[r0:r1, c0:c1][mask]
            share = float(np.count_nonzero((d >= cfg.min_depth_m) & (d <= cfg.max_depth_m))) / max(d.size, 1)
            if share < cfg.min_depth_fraction:
                reason = f"depth on {100 * share:.0f} % of the mask < {100 * cfg.min_depth_fraction:.0f} %"
                report.skipped.append(Skip(index, "little_depth", reason))
                log.debug("measure %s: skip instance %d (%s): %s", keyframe, index, inst.category, reason)
                continue
        if cfg.flush_tolerance_m > 0 and inst.category in cfg.raised_classes:
            relief = _relief(inst.mask, depth, cfg)
            if relief is not None and abs(relief) < cfg.flush_tolerance_m:
                reason = (f"flush with its surroundings ({100 * relief:+.1f} cm, a {inst.category} "
                          f"stands out more than {100 * cfg.flush_tolerance_m:.0f} cm)")
                report.skipped.append(Skip(index, "flush", reason))
                log.debug("measure %s: skip instance %d (%s): %s", keyframe, index, inst.category, reason)
                continue
        if kernel is not None:
            eroded = cv2.erode(mask.astype(np.uint8), kernel).astype(bool)
            if int(eroded.sum()) >= cfg.min_points:
                mask = eroded
        points_c = _back_project(mask, depth[r0:r1, c0:c1], (r0, c0), camera, cfg)
        if points_c.shape[0] >= cfg.min_points:
            points_c = points_c[_radius_inliers(points_c, cfg)]
            if cfg.cluster_gap_m > 0:
                points_c = points_c[_largest_cluster(points_c, cfg.cluster_gap_m)]
        if points_c.shape[0] < cfg.min_points:
            reason = f"{points_c.shape[0]} valid depth points < min_points {cfg.min_points}"
            report.skipped.append(Skip(index, "few_points", reason))
            log.debug("measure %s: skip instance %d (%s): %s", keyframe, index, inst.category, reason)
            continue
        points_g = points_c @ T_gc[:3, :3].T + T_gc[:3, 3]
        yaw, centre_g, size, source = _gravity_box(points_g, cfg)
        widest = max_width.get(inst.category)
        if widest is not None and size[0] > widest:
            keep = densest_window(points_g[:, :2] @ yaw_rotation(yaw)[:2, 0], widest)
            if int(keep.sum()) >= cfg.min_points:
                log.debug("measure %s: %s %.2f m wide > %.2f m: %d of %d points kept", keyframe,
                          inst.category, size[0], widest, int(keep.sum()), len(keep))
                points_c, points_g = points_c[keep], points_g[keep]
                yaw, centre_g, size, source = _gravity_box(points_g, cfg)
        usual = clipped_width.get(inst.category)
        if usual is not None and size[0] < usual:
            centre_g, size = _widen_at_border(centre_g, size, yaw, usual, inst.mask, T_gc, camera)
        T_world_object = np.eye(4)
        T_world_object[:3, :3] = R_wg @ yaw_rotation(yaw)
        T_world_object[:3, 3] = R_wg @ centre_g
        T_camera_object = T_cw @ T_world_object
        hist, descriptors = _appearance(image, inst.mask, cfg)
        log.debug("measure %s: %s yaw from %s, %d points", keyframe, inst.category, source, len(points_c))
        report.measurements.append(
            ObjectMeasurement(
                keyframe=keyframe,
                stamp=float(stamp),
                category=inst.category,
                confidence=float(inst.confidence),
                box_xyxy=np.asarray(inst.box_xyxy, dtype=np.float64),
                mask=inst.mask,
                points_camera=points_c.astype(np.float32),
                T_camera_object=T_camera_object,
                T_world_camera=T_wc,
                T_world_object=T_world_object,
                size=size,
                color_hist=hist,
                descriptors=descriptors,
                gt_instance=inst.gt_instance,
            )
        )
    if report.skipped:
        log.debug("measure %s: %d of %d instance(s) skipped", keyframe, len(report.skipped), len(instances))
    return report


def _relief(mask: NDArray[np.bool_], depth: NDArray[np.float32], cfg: MeasureConfig) -> float | None:
    """Median depth of a ring around ``mask`` minus the mask's median depth, metres.

    The ring starts 2 px outside the mask (mixed depth at the border) and is
    ``cfg.flush_ring_px`` wide. Positive: the object stands in front of its surroundings.
    None when the mask or the ring has fewer than ``cfg.min_points`` valid depths.
    """
    around = ring_around(mask, cfg.flush_ring_px)
    if around is None:
        return None
    window, m, ring = around
    d = depth[window]
    valid = (d >= cfg.min_depth_m) & (d <= cfg.max_depth_m)
    inside = d[m & valid]
    outside = d[ring & valid]
    if inside.size < cfg.min_points or outside.size < cfg.min_points:
        return None
    return float(np.median(outside) - np.median(inside))


def measure_instances(
    instances: Sequence[Instance],
    *,
    bgr: NDArray[np.uint8],
    depth_m: NDArray[np.float32],
    camera: PinholeCamera,
    T_world_camera: ArrayLike,
    keyframe: str,
    stamp: float,
    config: MeasureConfig | None = None,
    gravity_world: ArrayLike = (0.0, 0.0, -1.0),
) -> list[ObjectMeasurement]:
    """3D measurements (class, 6-DoF gravity-aligned pose, size, appearance) of one keyframe's instances.

    Args:
        instances: masks in the colour image of this keyframe.
        bgr: uint8 (H, W, 3) colour image, BGR order (OpenCV).
        depth_m: float32 (H, W) depth along the camera z axis, metres, registered to the
            colour camera; 0 = no measurement.
        camera: the colour camera's intrinsics (H, W must match the images).
        T_world_camera: (4, 4) float64 camera pose in ``world`` (odom on the server).
        keyframe: keyframe key stored in each measurement.
        stamp: keyframe time, seconds.
        config: :class:`MeasureConfig` (defaults when None).
        gravity_world: (3,) gravity direction in ``world`` (any length); the object z axis
            is its opposite.

    Returns:
        Measurements of the instances with at least ``config.min_points`` inlier points, in
        input order. Skipped instances are logged at debug level; use
        :func:`measure_instances_report` to get them with their reasons.

    Raises:
        GeometryError: image, depth, mask or transform shapes do not match.
    """
    return measure_instances_report(
        instances,
        bgr=bgr,
        depth_m=depth_m,
        camera=camera,
        T_world_camera=T_world_camera,
        keyframe=keyframe,
        stamp=stamp,
        config=config,
        gravity_world=gravity_world,
    ).measurements
