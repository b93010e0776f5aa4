"""Tests of wardmap.shared.semantic: semantic descriptors and dynamic points (paper 001 Eq. 2, 6-8)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from wardmap.shared.config import from_mapping
from wardmap.shared.errors import ConfigError, GeometryError, KnowledgeGraphError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.semantic import (
    DynamicResult,
    SemanticConfig,
    dynamic_mask,
    moving_counts,
    semantic_descriptors,
    semantic_distance,
)

N = 21
DELTA = 55


@pytest.fixture(scope="module")
def kg() -> KnowledgeGraph:
    return KnowledgeGraph.load()


def blob_image(rng: np.random.Generator, size: int = 240, shapes: int = 14) -> np.ndarray:
    """A label image of large random rectangles and discs with classes 1..13 on background."""
    image = np.zeros((size, size), dtype=np.uint8)
    for _ in range(shapes):
        cls = int(rng.integers(1, 14))
        centre = rng.integers(size // 2 - 30, size // 2 + 30, 2)
        if rng.random() < 0.5:
            half = rng.integers(8, 30, 2)
            p0 = (int(centre[0] - half[0]), int(centre[1] - half[1]))
            p1 = (int(centre[0] + half[0]), int(centre[1] + half[1]))
            cv2.rectangle(image, p0, p1, cls, thickness=-1)
        else:
            cv2.circle(image, (int(centre[0]), int(centre[1])), int(rng.integers(8, 30)), cls, thickness=-1)
    return image


def rotate_about(image: np.ndarray, centre: tuple[float, float], angle_deg: float) -> np.ndarray:
    """Rotate ``image`` counter-clockwise on screen by ``angle_deg`` about ``centre`` (nearest)."""
    M = cv2.getRotationMatrix2D(centre, angle_deg, 1.0)
    return cv2.warpAffine(image, M, (image.shape[1], image.shape[0]), flags=cv2.INTER_NEAREST,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def reference_descriptors(image: np.ndarray, uv: np.ndarray, angle_deg: np.ndarray, n: int) -> np.ndarray:
    """Straightforward per-cell implementation of the rotated patch (module docstring rule)."""
    H, W = image.shape
    half = n // 2
    out = np.zeros((len(uv), n, n), dtype=np.uint8)
    for k, ((u, v), a) in enumerate(zip(uv, angle_deg, strict=True)):
        c, s = np.cos(np.deg2rad(a)), np.sin(np.deg2rad(a))
        for i in range(n):
            for j in range(n):
                du, dv = j - half, i - half
                col = int(np.floor(u + c * du - s * dv + 0.5))
                row = int(np.floor(v + s * du + c * dv + 0.5))
                if 0 <= col < W and 0 <= row < H:
                    out[k, i, j] = image[row, col]
    return out


# ------------------------------------------------------------------------- descriptors


def test_descriptor_matches_reference_implementation() -> None:
    """Scenario: random label image, random key points (some near or outside the border) and
    angles; the fast kernel equals a per-cell reference implementation exactly."""
    rng = np.random.default_rng(1)
    image = rng.integers(0, 14, (60, 80)).astype(np.uint8)
    uv = rng.uniform([-5, -5], [85, 65], (40, 2))
    angles = rng.uniform(-360, 360, 40)
    got = semantic_descriptors(image, uv, angles, n=9)
    assert got.dtype == np.uint8 and got.shape == (40, 9, 9)
    np.testing.assert_array_equal(got, reference_descriptors(image, uv, angles, 9))


def test_descriptor_at_angle_zero_is_the_axis_aligned_patch() -> None:
    """Scenario: angle 0 and an integer key point: the descriptor is the plain image crop."""
    rng = np.random.default_rng(2)
    image = rng.integers(0, 14, (50, 50)).astype(np.uint16)
    desc = semantic_descriptors(image, np.array([[25.0, 20.0]]), np.array([0.0]), n=N)
    np.testing.assert_array_equal(desc[0], image[10:31, 15:36].astype(np.uint8))


def test_cells_outside_the_image_are_background() -> None:
    """Scenario: a key point on the top-left pixel of a uniform class-3 image, angle 0: only
    the 11 x 11 quadrant of non-negative offsets lies inside the image."""
    image = np.full((40, 40), 3, dtype=np.uint8)
    desc = semantic_descriptors(image, np.array([[0.0, 0.0]]), np.array([0.0]), n=N)[0]
    assert np.count_nonzero(desc == 3) == 11 * 11
    assert np.all(desc[10:, 10:] == 3) and np.all(desc[:10, :] == 0) and np.all(desc[:, :10] == 0)


def test_rotation_by_90_degrees_gives_identical_descriptors() -> None:
    """Scenario: a blob label image is rotated by +-90 deg (cv2.warpAffine, nearest) about an
    integer key point and the ORB angle turns with it (a CCW on-screen rotation by alpha
    changes the image-frame angle by -alpha): the descriptors agree exactly. The angle
    23.7 deg avoids exact rounding ties, which nearest sampling breaks asymmetrically."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        image = blob_image(rng)
        uv = np.array([[120.0, 120.0]])
        angle = 23.7
        before = semantic_descriptors(image, uv, np.array([angle]), n=N)
        for alpha in (90.0, -90.0, 180.0):
            rotated = rotate_about(image, (120.0, 120.0), alpha)
            after = semantic_descriptors(rotated, uv, np.array([angle - alpha]), n=N)
            np.testing.assert_array_equal(after, before)


@pytest.mark.parametrize("alpha", [37.0, -61.5, 145.0])
def test_rotation_by_arbitrary_angles_keeps_95_percent_of_cells(alpha: float) -> None:
    """Scenario: the blob image rotated by a non-right angle about the key point (nearest
    resampling moves region borders by up to a pixel): at least 95% of the descriptor cells
    agree, while the unrotated descriptor of the rotated image differs clearly (so the
    check is not vacuous)."""
    rng = np.random.default_rng(4)
    uv = np.array([[120.0, 120.0]])
    agreements, naive = [], []
    for _ in range(8):
        image = blob_image(rng)
        angle = float(rng.uniform(0, 360))
        before = semantic_descriptors(image, uv, np.array([angle]), n=N)
        rotated = rotate_about(image, (120.0, 120.0), alpha)
        after = semantic_descriptors(rotated, uv, np.array([angle - alpha]), n=N)
        unturned = semantic_descriptors(rotated, uv, np.array([angle]), n=N)
        agreements.append(1 - semantic_distance(before, after)[0] / N**2)
        naive.append(1 - semantic_distance(before, unturned)[0] / N**2)
    assert min(agreements) >= 0.95, agreements
    assert np.mean(naive) < np.mean(agreements) - 0.05


def test_descriptor_rejects_bad_input() -> None:
    """Scenario: wrong shapes, dtypes, even n, non-finite points, classes above 255."""
    image = np.zeros((10, 10), dtype=np.uint8)
    with pytest.raises(GeometryError):
        semantic_descriptors(image.astype(np.float32), np.zeros((1, 2)), np.zeros(1))
    with pytest.raises(GeometryError):
        semantic_descriptors(image, np.zeros((1, 3)), np.zeros(1))
    with pytest.raises(GeometryError):
        semantic_descriptors(image, np.zeros((2, 2)), np.zeros(1))
    with pytest.raises(GeometryError):
        semantic_descriptors(image, np.zeros((1, 2)), np.zeros(1), n=20)
    with pytest.raises(GeometryError):
        semantic_descriptors(image, np.array([[np.nan, 1.0]]), np.zeros(1))
    with pytest.raises(GeometryError):
        semantic_descriptors(np.full((10, 10), 300, dtype=np.uint16), np.array([[5.0, 5.0]]), np.zeros(1))
    assert semantic_descriptors(image, np.zeros((0, 2)), np.zeros(0)).shape == (0, N, N)


# ------------------------------------------------------------------------- Eq. 7 and 8


def scene(kg: KnowledgeGraph, base: str | None, person_cells: int) -> np.ndarray:
    """100 x 100 label image: class ``base`` in rows/cols 30..70 (background if None), and a
    person block of exactly ``person_cells`` pixels inside the 21 x 21 patch of the key
    point (50, 50) but away from the key point itself (rows 40..44, from column 41 on)."""
    image = np.zeros((100, 100), dtype=np.uint8)
    if base is not None:
        image[30:71, 30:71] = kg.index_of(base)
    person = kg.index_of("person")
    rows, rest = divmod(person_cells, 19)
    image[40:40 + rows, 41:60] = person
    image[40 + rows, 41:41 + rest] = person
    return image


KP = np.array([[50.0, 50.0]])


def test_moving_counts_count_person_cells(kg: KnowledgeGraph) -> None:
    """Scenario: Eq. 7 on the crafted scene: N equals the number of person pixels placed in
    the (angle 0) patch."""
    lut = kg.mobility_lut()
    for cells in (0, 1, 55, 56, 94):
        desc = semantic_descriptors(scene(kg, "wheelchair", cells), KP, np.zeros(1), n=N)
        assert moving_counts(desc, lut).tolist() == [cells]


def test_point_on_a_person_is_dynamic(kg: KnowledgeGraph) -> None:
    """Scenario: the key point lies on a person (moving class): dynamic, whatever is around."""
    result = dynamic_mask(scene(kg, "person", 0), KP, np.zeros(1), kg.mobility_lut(), n=N, delta=DELTA)
    assert isinstance(result, DynamicResult)
    assert result.dynamic.tolist() == [True]
    assert result.point_class.tolist() == [kg.index_of("person")]
    assert result.descriptors.shape == (1, N, N)


@pytest.mark.parametrize(("cells", "dynamic"), [(56, True), (94, True), (55, False), (30, False), (0, False)])
def test_movable_point_is_dynamic_only_with_more_than_delta_person_cells(
    kg: KnowledgeGraph, cells: int, dynamic: bool
) -> None:
    """Scenario: key point on a wheelchair (movable) with a person covering ``cells`` of its
    descriptor: dynamic iff cells > delta = 55 (strictly; exactly 55 stays static)."""
    result = dynamic_mask(scene(kg, "wheelchair", cells), KP, np.zeros(1), kg.mobility_lut(), n=N,
                          delta=DELTA)
    assert result.point_class.tolist() == [kg.index_of("wheelchair")]
    assert result.dynamic.tolist() == [dynamic]


@pytest.mark.parametrize("base", ["door", "bed", None])
def test_static_and_background_points_stay_static_next_to_people(
    kg: KnowledgeGraph, base: str | None
) -> None:
    """Scenario: key point on a door, a bed (static) or the background with a person covering
    94 cells of its descriptor: static (only movable things are moved by people)."""
    result = dynamic_mask(scene(kg, base, 94), KP, np.zeros(1), kg.mobility_lut(), n=N, delta=DELTA)
    assert result.dynamic.tolist() == [False]


def test_dynamic_mask_is_vectorised_over_points(kg: KnowledgeGraph) -> None:
    """Scenario: several key points in one image give the same decisions as one at a time."""
    rng = np.random.default_rng(5)
    image = blob_image(rng, size=200)
    image[rng.random(image.shape) < 0.02] = kg.index_of("person")
    uv = rng.uniform(0, 200, (200, 2))
    angles = rng.uniform(0, 360, 200)
    lut = kg.mobility_lut()
    together = dynamic_mask(image, uv, angles, lut, n=N, delta=10)
    for k in range(0, 200, 17):
        alone = dynamic_mask(image, uv[k:k + 1], angles[k:k + 1], lut, n=N, delta=10)
        assert alone.dynamic[0] == together.dynamic[k]
        np.testing.assert_array_equal(alone.descriptors[0], together.descriptors[k])


def test_class_outside_the_lut_is_an_error(kg: KnowledgeGraph) -> None:
    """Scenario: a class image holding index 200, beyond the knowledge graph's classes."""
    image = np.full((30, 30), 200, dtype=np.uint8)
    with pytest.raises(KnowledgeGraphError):
        dynamic_mask(image, np.array([[15.0, 15.0]]), np.zeros(1), kg.mobility_lut())


# ------------------------------------------------------------------------- Eq. 6


def test_semantic_distance_identical_and_fully_different() -> None:
    """Scenario: identical descriptors are at distance 0; descriptors differing in every cell
    at distance n*n."""
    rng = np.random.default_rng(6)
    a = rng.integers(0, 14, (4, N, N)).astype(np.uint8)
    assert semantic_distance(a, a).tolist() == [0, 0, 0, 0]
    b = ((a + 1) % 14).astype(np.uint8)
    assert semantic_distance(a, b).tolist() == [N * N] * 4


def test_semantic_distance_reproduces_fig4() -> None:
    """Scenario: the two 5 x 5 descriptors of paper 001 Fig. 4, symbols as distinct values
    (C1..C4, Ci, and the key points P, P'): they differ in the top-row cell C1 vs C3 and in
    the centre P vs P', and the paper states their distance is 2."""
    C1, C2, C3, C4, Ci, P, Pp = 1, 2, 3, 4, 5, 6, 7
    left = np.array([[C1, C1, C1, C3, C3],
                     [C2, C1, C1, C3, C3],
                     [C2, C2, P, C3, C4],
                     [C2, Ci, Ci, C4, C4],
                     [Ci, Ci, C4, C4, C4]], dtype=np.uint8)
    right = np.array([[C1, C1, C3, C3, C3],
                      [C2, C1, C1, C3, C3],
                      [C2, C2, Pp, C3, C4],
                      [C2, Ci, Ci, C4, C4],
                      [Ci, Ci, C4, C4, C4]], dtype=np.uint8)
    assert semantic_distance(left[None], right[None]).tolist() == [2]
    assert semantic_distance(left[None], right[None])[0] <= SemanticConfig().max_semantic_distance


def test_semantic_distance_rejects_mismatched_shapes() -> None:
    """Scenario: descriptor stacks of different shapes or dtype."""
    with pytest.raises(GeometryError):
        semantic_distance(np.zeros((2, 5, 5), np.uint8), np.zeros((2, 7, 7), np.uint8))
    with pytest.raises(GeometryError):
        semantic_distance(np.zeros((2, 5, 5), np.int32), np.zeros((2, 5, 5), np.int32))


# ------------------------------------------------------------------------- config


def test_semantic_config_defaults_follow_the_paper() -> None:
    """Scenario: defaults are paper 001's n = 21, delta = 55, distance gate 110."""
    cfg = SemanticConfig()
    assert (cfg.n, cfg.delta, cfg.max_semantic_distance, cfg.enabled) == (21, 55, 110, True)


@pytest.mark.parametrize("data", [{"n": 20}, {"n": 0}, {"delta": -1}, {"delta": 500},
                                  {"max_semantic_distance": 442}, {"n": 5, "delta": 30}])
def test_semantic_config_rejects_bad_values(data: dict[str, int]) -> None:
    """Scenario: even or non-positive n, thresholds outside 0..n*n, loaded from a mapping."""
    with pytest.raises(ConfigError):
        from_mapping(SemanticConfig, data, prefix="semantic")
