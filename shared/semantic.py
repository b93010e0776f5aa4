"""Local semantic descriptors and dynamic key points (paper 001 Sec. 3.3-3.4, Eq. 2, 6-8).

A *semantic descriptor* (Eq. 2) is the ``n x n`` patch of class indices centred on a
key point, sampled on a grid rotated by the key point's ORB orientation so that it is
rotation invariant (Sec. 3.3, Fig. 4 step 4). With the knowledge graph's mobility codes
(:meth:`~wardmap.shared.knowledge.KnowledgeGraph.mobility_lut`: 0 static, 1 movable,
2 moving) it decides which key points are dynamic (Sec. 3.4, Eq. 7-8); the number of
differing cells between two descriptors rejects implausible matches (Eq. 6).

Conventions:

- ``class_image``: (H, W) integer class index per pixel, 0 = background, indices into
  the mobility LUT (the knowledge graph's segmentation labels).
- ``uv``: (N, 2) key-point pixel coordinates ``(u, v)``; u along columns, v along rows,
  the centre of the top-left pixel at (0, 0) (OpenCV's ``KeyPoint.pt``).
- ``angle_deg``: (N,) ORB orientation in degrees (OpenCV's ``KeyPoint.angle``): the
  direction of the intensity centroid (Eq. 3-5), measured in image coordinates from the
  +u axis towards the +v axis (clockwise on screen).
- Descriptor cell ``[i, j]`` has patch offsets ``(du, dv) = (j - n//2, i - n//2)``
  in the key point's own frame and samples the pixel nearest to
  ``(u + du cos a - dv sin a, v + du sin a + dv cos a)``: the same rotation ORB applies
  to its BRIEF pattern. Cells outside the image read as background (0).

Everything here is pure array code (numpy, plus one numba loop for the sampling): new
arrays out, inputs never modified.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.errors import ConfigError, GeometryError, KnowledgeGraphError

__all__ = [
    "MOVABLE_CODE",
    "MOVING_CODE",
    "DynamicResult",
    "SemanticConfig",
    "dynamic_mask",
    "moving_counts",
    "semantic_descriptors",
    "semantic_distance",
]

U8 = NDArray[np.uint8]
I64 = NDArray[np.int64]
Bool = NDArray[np.bool_]

MOVABLE_CODE: Final = 1
"""Mobility code of ``P_movable`` classes in the knowledge graph's mobility LUT."""
MOVING_CODE: Final = 2
"""Mobility code of ``P_moving`` classes (people) in the knowledge graph's mobility LUT."""


@dataclass(frozen=True)
class SemanticConfig:
    """Parameters of the semantic descriptor and dynamic-point test (paper 001 Sec. 3.3-4).

    Raises:
        ConfigError: on an even or non-positive ``n`` or a threshold outside 0..n*n.
    """

    n: int = 21
    """Side length of the descriptor patch in pixels; odd, so the key point is the centre
    cell (Eq. 2). Paper 001 Sec. 4 uses 21 and finds 10..49 works."""
    delta: int = 55
    """Eq. 8 threshold: a key point on a movable class is dynamic when strictly more than
    ``delta`` descriptor cells are moving (people). Paper 001 uses 55 for n = 21 and
    recommends 1/8..1/2 of the descriptor size."""
    max_semantic_distance: int = 110
    """Eq. 6 gate: a match whose descriptors differ in more than this many cells is an
    outlier (paper 001 Sec. 4.4: 110 for n = 21)."""
    enabled: bool = True
    """When False the frontend skips semantic dynamic-point removal and the match gate."""

    def __post_init__(self) -> None:
        if isinstance(self.n, bool) or not isinstance(self.n, int) or self.n < 1 or self.n % 2 == 0:
            raise ConfigError(f"semantic.n must be a positive odd integer, got {self.n!r}")
        cells = self.n * self.n
        for name in ("delta", "max_semantic_distance"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= cells:
                raise ConfigError(
                    f"semantic.{name} must be an integer in 0..{cells} (n*n for n = {self.n}), "
                    f"got {value!r}"
                )
        if not isinstance(self.enabled, bool):
            raise ConfigError(f"semantic.enabled must be true or false, got {self.enabled!r}")


@dataclass(frozen=True, eq=False)
class DynamicResult:
    """Outcome of :func:`dynamic_mask` for N key points.

    Attributes:
        dynamic: bool (N,), True where Eq. 8 marks the key point dynamic (``S_p = 1``).
        descriptors: uint8 (N, n, n) rotated semantic descriptors (Eq. 2).
        point_class: uint8 (N,) class index at the key point's own pixel (the centre cell).
    """

    dynamic: Bool
    descriptors: U8
    point_class: U8


def semantic_descriptors(class_image: ArrayLike, uv: ArrayLike, angle_deg: ArrayLike, n: int = 21) -> U8:
    """Rotated semantic descriptors ``D^{n x n}`` of N key points (paper 001 Eq. 2, Fig. 4).

    Args:
        class_image: (H, W) uint8 or uint16 class index per pixel (0 = background);
            values must fit in uint8 (at most 255) where sampled.
        uv: (N, 2) key-point pixel coordinates ``(u, v)``, finite.
        angle_deg: (N,) ORB orientations in degrees (module docstring for the sense).
        n: odd patch side length in pixels.

    Returns:
        A new uint8 (N, n, n) array: ``[k, i, j]`` is the class at patch offset
        ``(j - n//2, i - n//2)`` in key point k's rotated frame, nearest-neighbour
        sampled; 0 outside the image. Rotating the image about a key point and its
        angle with it leaves the descriptor unchanged up to resampling.

    Raises:
        GeometryError: on wrong shapes or dtypes, non-finite inputs, a bad ``n``, or a
            sampled class above 255.
    """
    image = _check_class_image(class_image)
    points, angles = _check_keypoints(uv, angle_deg)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1 or n % 2 == 0:
        raise GeometryError(f"semantic_descriptors: n must be a positive odd integer, got {n!r}")
    count = points.shape[0]
    if count == 0:
        return np.zeros((0, n, n), dtype=np.uint8)
    theta = np.deg2rad(angles)
    samples = np.empty((count, n, n), dtype=image.dtype)
    _sample_rotated(np.ascontiguousarray(image), points, np.cos(theta), np.sin(theta), samples)
    if samples.dtype != np.uint8:
        top = int(samples.max())
        if top > 255:
            raise GeometryError(
                f"semantic_descriptors: class index {top} does not fit a uint8 descriptor (max 255)"
            )
        return samples.astype(np.uint8)
    return samples


def moving_counts(descriptors: ArrayLike, mobility_lut: ArrayLike) -> I64:
    """Number of descriptor cells whose class is moving: ``N`` of paper 001 Eq. 7.

    The paper counts cells equal to ``c_person``; here every class with the moving code
    (:data:`MOVING_CODE`, ``P_moving``) counts, which is the same for the hospital graph
    where people are the only moving class.

    Args:
        descriptors: uint8 (N, n, n) semantic descriptors.
        mobility_lut: (C,) mobility code per class index (0 static, 1 movable, 2 moving).

    Returns:
        A new int64 (N,) array of counts in 0..n*n.

    Raises:
        GeometryError: on wrong shapes or dtypes.
        KnowledgeGraphError: a descriptor holds a class index outside the LUT.
    """
    desc = _check_descriptors(descriptors, "descriptors")
    lut = _check_lut(mobility_lut)
    _check_classes_in_lut(desc, lut)
    is_moving = np.zeros(256, dtype=np.bool_)
    is_moving[: lut.shape[0]] = lut == MOVING_CODE
    return _count_flagged(np.ascontiguousarray(desc.reshape(desc.shape[0], -1)), is_moving)


def dynamic_mask(
    class_image: ArrayLike,
    uv: ArrayLike,
    angle_deg: ArrayLike,
    mobility_lut: ArrayLike,
    n: int = 21,
    delta: int = 55,
) -> DynamicResult:
    """Mark dynamic key points with the knowledge graph and semantic descriptors (Eq. 8).

    A key point is dynamic (``S_p = 1``) when the class at its own pixel is moving
    (``p in P_person``), or when that class is movable (``p in P_movable``) and strictly
    more than ``delta`` cells of its descriptor are moving (``N_p > delta``, Eq. 7);
    otherwise (static classes, background, movable things with few people around) it is
    static.

    Args:
        class_image: (H, W) uint8/uint16 class index per pixel, 0 = background.
        uv: (N, 2) key-point pixel coordinates ``(u, v)``.
        angle_deg: (N,) ORB orientations in degrees.
        mobility_lut: (C,) mobility code per class index, C > max class in the image
            (:meth:`~wardmap.shared.knowledge.KnowledgeGraph.mobility_lut`).
        n: odd descriptor side length (:attr:`SemanticConfig.n`).
        delta: Eq. 8 threshold (:attr:`SemanticConfig.delta`).

    Returns:
        A :class:`DynamicResult` with the mask, the descriptors and each point's class.

    Raises:
        GeometryError: on wrong shapes, dtypes or values.
        KnowledgeGraphError: a sampled class index is outside the LUT.
    """
    if isinstance(delta, bool) or not isinstance(delta, int) or delta < 0:
        raise GeometryError(f"dynamic_mask: delta must be a non-negative integer, got {delta!r}")
    lut = _check_lut(mobility_lut)
    descriptors = semantic_descriptors(class_image, uv, angle_deg, n)
    half = n // 2
    point_class = descriptors[:, half, half].copy()
    counts = moving_counts(descriptors, lut)
    code = lut[point_class]
    # Eq. 8: S_p = 1 for p in P_person, or p in P_movable with N_p > delta.
    dynamic = (code == MOVING_CODE) | ((code == MOVABLE_CODE) & (counts > delta))
    return DynamicResult(dynamic=dynamic, descriptors=descriptors, point_class=point_class)


def semantic_distance(desc_a: ArrayLike, desc_b: ArrayLike) -> I64:
    """Semantic distance between paired descriptors: the number of differing cells (Eq. 6).

    Paper 001 prints Eq. 6 as ``sum 1(|f_p(x_i, y_j) - f_p'(x'_i, y'_j)| < 1)``, which
    counts cells with *equal* class. Its own worked example (Fig. 4) calls the result for
    two nearly identical 5 x 5 descriptors "the distance ... is 2", which is the number
    of *differing* cells (one cell ``C1`` vs ``C3`` plus the centres ``P`` vs ``P'``),
    and Sec. 4.4 rejects a match when the distance is *larger* than 110 (n = 21). Both
    only make sense for a count of disagreements, so this function implements
    ``sum 1(f_p(x_i, y_j) != f_p'(x'_i, y'_j))``: 0 for identical descriptors, n*n for
    descriptors that differ everywhere. A match is kept when the result is at most
    :attr:`SemanticConfig.max_semantic_distance`.

    Args:
        desc_a, desc_b: uint8 (N, n, n) descriptors; row k of each forms one pair.

    Returns:
        A new int64 (N,) array of distances in 0..n*n.

    Raises:
        GeometryError: the shapes differ or are not (N, n, n).
    """
    a = _check_descriptors(desc_a, "desc_a")
    b = _check_descriptors(desc_b, "desc_b")
    if a.shape != b.shape:
        raise GeometryError(f"semantic_distance: desc_a and desc_b must have the same shape, got "
                            f"{a.shape} and {b.shape}")
    return np.count_nonzero(a != b, axis=(1, 2)).astype(np.int64)


# ---------------------------------------------------------------------------- kernel


@njit(cache=True, nogil=True, error_model="numpy")
def _sample_rotated(image: NDArray[Any], points: NDArray[np.float64], cos_t: NDArray[np.float64],
                    sin_t: NDArray[np.float64], out: NDArray[Any]) -> None:  # pragma: no cover - jit
    """Fill ``out`` (N, n, n) with nearest-neighbour samples of ``image`` on rotated grids.

    Sec. 3.3 / Fig. 4 step 4: cell (i, j) has offsets (du, dv) = (j - n//2, i - n//2) in
    the key point's frame, rotated by the key point's angle into the image; samples
    outside the image are background (0). A plain loop (numba) is about ten times faster
    than the equivalent numpy broadcasting, which allocates several (N, n*n) temporaries.
    """
    height, width = image.shape
    n = out.shape[1]
    half = n // 2
    for k in range(points.shape[0]):
        u = points[k, 0]
        v = points[k, 1]
        c = cos_t[k]
        s = sin_t[k]
        for i in range(n):
            dv = i - half
            for j in range(n):
                du = j - half
                col = np.floor(u + c * du - s * dv + 0.5)
                row = np.floor(v + s * du + c * dv + 0.5)
                if 0.0 <= col < width and 0.0 <= row < height:
                    out[k, i, j] = image[int(row), int(col)]
                else:
                    out[k, i, j] = 0


@njit(cache=True, nogil=True)
def _count_flagged(cells: NDArray[np.uint8], flagged: NDArray[np.bool_]) -> I64:  # pragma: no cover - jit
    """Per row of ``cells`` (N, m), how many cells have a class with ``flagged[class]`` (256,)."""
    out = np.zeros(cells.shape[0], np.int64)
    for k in range(cells.shape[0]):
        count = 0
        for c in cells[k]:
            if flagged[c]:
                count += 1
        out[k] = count
    return out


# ---------------------------------------------------------------------------- checks


def _check_class_image(class_image: ArrayLike) -> NDArray[np.uint8] | NDArray[np.uint16]:
    image = np.asarray(class_image)
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise GeometryError(f"class_image must be a uint8 or uint16 (H, W) array, got {image.dtype} "
                            f"{image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise GeometryError(f"class_image must not be empty, got {image.shape}")
    return image


def _check_keypoints(uv: ArrayLike, angle_deg: ArrayLike) -> tuple[NDArray[np.float64],
                                                                    NDArray[np.float64]]:
    points = np.asarray(uv, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise GeometryError(f"uv must be an (N, 2) array of pixel coordinates, got {points.shape}")
    angles = np.asarray(angle_deg, dtype=np.float64)
    if angles.shape != (points.shape[0],):
        raise GeometryError(f"angle_deg must be ({points.shape[0]},) to match uv, got {angles.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(angles))):
        raise GeometryError("uv and angle_deg must be finite")
    return points, angles


def _check_descriptors(descriptors: ArrayLike, name: str) -> U8:
    desc = np.asarray(descriptors)
    if desc.ndim != 3 or desc.shape[1] != desc.shape[2] or desc.dtype != np.uint8:
        raise GeometryError(f"{name} must be a uint8 (N, n, n) array, got {desc.dtype} {desc.shape}")
    return desc


def _check_lut(mobility_lut: ArrayLike) -> U8:
    lut = np.asarray(mobility_lut)
    if lut.ndim != 1 or lut.shape[0] == 0 or not np.issubdtype(lut.dtype, np.integer):
        raise GeometryError(f"mobility_lut must be a non-empty integer (C,) array, got {lut.dtype} "
                            f"{lut.shape}")
    if lut.shape[0] > 256:
        raise GeometryError(f"mobility_lut has {lut.shape[0]} classes; descriptors hold at most 256")
    if np.any((lut < 0) | (lut > MOVING_CODE)):
        raise GeometryError("mobility_lut codes must be 0 (static), 1 (movable) or 2 (moving)")
    return lut.astype(np.uint8)


def _check_classes_in_lut(desc: U8, lut: U8) -> None:
    if desc.size and int(desc.max()) >= lut.shape[0]:
        raise KnowledgeGraphError(
            f"class index {int(desc.max())} is not in the mobility LUT (classes 0..{lut.shape[0] - 1})"
        )
