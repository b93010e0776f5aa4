"""ORB grid extraction, adaptive thermal SIFT and descriptor matching (``wardmap.edge.features``).

Images are synthetic and seeded: random filled rectangles and circles drawn with cv2
give corners everywhere they are drawn; blank regions give none.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from wardmap.edge.features import (
    Features,
    OrbConfig,
    OrbExtractor,
    SiftConfig,
    _water_fill,
    extract_orb,
    extract_sift_adaptive,
    match_descriptors,
    match_projected,
    thermal_to_gray8,
)
from wardmap.shared.errors import ConfigError, GeometryError

U8 = NDArray[np.uint8]
TUM_RGB = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tum_fr1_rpy_s3_first100" / "rgb"


# --------------------------------------------------------------------------- helpers


def _shapes(h: int, w: int, n: int, seed: int, small: bool = False) -> NDArray[np.float32]:
    """Float image in [0, 1] of ``n`` random filled rectangles and circles."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    r_hi, s_hi = (10, 15) if small else (30, 60)
    for _ in range(n):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        val = float(rng.uniform(0.0, 1.0))
        if rng.random() < 0.5:
            cv2.circle(img, c, int(rng.integers(2, r_hi)), val, -1)
        else:
            size = rng.integers(3, s_hi, size=2)
            cv2.rectangle(img, c, (c[0] + int(size[0]), c[1] + int(size[1])), val, -1)
    return img


def _textured(h: int = 480, w: int = 640, seed: int = 0) -> U8:
    """A 640x480 grey image full of corners (shapes on a mid-grey background)."""
    img = 0.15 + 0.7 * _shapes(h, w, 1500, seed)
    return np.clip(img * 255.0, 0, 255).astype(np.uint8)


def _cell_counts(f: Features, cfg: OrbConfig, h: int = 480, w: int = 640) -> NDArray[np.int64]:
    """Features per grid cell (rows, cols), from their level-0 positions (paper 003 Eq. 4)."""
    col = np.minimum((f.uv[:, 0] * cfg.grid_cols / w).astype(int), cfg.grid_cols - 1)
    row = np.minimum((f.uv[:, 1] * cfg.grid_rows / h).astype(int), cfg.grid_rows - 1)
    counts = np.zeros((cfg.grid_rows, cfg.grid_cols), np.int64)
    np.add.at(counts, (row, col), 1)
    return counts


def _orb_features(uv: NDArray[np.float64], desc: U8, octave: NDArray[np.int64] | None = None) -> Features:
    n = uv.shape[0]
    return Features(
        uv=uv.astype(np.float32),
        angle_deg=np.zeros(n, np.float32),
        response=np.ones(n, np.float32),
        octave=(np.zeros(n) if octave is None else octave).astype(np.int32),
        size=np.full(n, 31.0, np.float32),
        descriptors=desc,
        kind="orb",
    )


def _flip_bits(desc: U8, n_bits: int, rng: np.random.Generator) -> U8:
    """Copy of descriptors (M, 32) with ``n_bits`` random distinct bits flipped per row."""
    bits = np.unpackbits(desc, axis=1)
    for row in bits:
        idx = rng.choice(256, size=n_bits, replace=False)
        row[idx] ^= 1
    return np.packbits(bits, axis=1)


# --------------------------------------------------------------------------- ORB


def test_orb_textured_image_fills_quota_and_spreads_over_grid() -> None:
    """Textured 640x480 frame: close to n_features, every cell gets keypoints, none hogs them.

    Per-cell quota is Q / (G_col G_row) = 1000 / 48 (paper 003 Eq. 3); with texture
    everywhere no cell should need redistributed quota, so the max stays near it.
    """
    cfg = OrbConfig()
    f = extract_orb(_textured(), cfg)
    assert 0.95 * cfg.n_features <= len(f) <= cfg.n_features
    counts = _cell_counts(f, cfg)
    quota = cfg.n_features / (cfg.grid_cols * cfg.grid_rows)
    assert counts.min() >= 0.5 * quota, counts
    assert counts.max() <= 1.5 * quota, counts
    assert set(np.unique(f.octave)) == set(range(cfg.n_levels))


def test_orb_feature_arrays_have_documented_shapes_and_ranges() -> None:
    """Every field has N rows and the documented dtype; keypoints keep the edge margin."""
    cfg = OrbConfig(n_features=500)
    f = OrbExtractor(cfg).extract(_textured(seed=1))
    n = len(f)
    assert f.kind == "orb" and n > 0
    assert f.uv.dtype == np.float32 and f.uv.shape == (n, 2)
    assert f.descriptors.dtype == np.uint8 and f.descriptors.shape == (n, 32)
    assert f.angle_deg.dtype == np.float32 and np.all((f.angle_deg >= 0) & (f.angle_deg < 360))
    assert np.all(np.diff(f.octave) >= 0), "ordered by pyramid level"
    np.testing.assert_allclose(f.size, 31.0 * cfg.scale_factor**f.octave, rtol=1e-5)
    margin = cfg.edge_margin * cfg.scale_factor**f.octave
    assert np.all(f.uv[:, 0] >= margin - 1) and np.all(f.uv[:, 0] <= 640 - margin + 1)
    assert np.all(f.uv[:, 1] >= margin - 1) and np.all(f.uv[:, 1] <= 480 - margin + 1)


def test_orb_is_deterministic() -> None:
    """The same frame twice gives identical features (no hidden state between frames)."""
    ex = OrbExtractor()
    img = _textured(seed=2)
    a, b = ex.extract(img), ex.extract(img)
    np.testing.assert_array_equal(a.uv, b.uv)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)


def test_orb_redistributes_quota_of_empty_cells() -> None:
    """Texture only in the left half: the empty right half's quota goes to the left cells.

    The frame still gets close to n_features, the empty cells get none, and no textured
    cell takes more than about twice its quota (the right half is half the grid).
    """
    cfg = OrbConfig()
    img = _textured(seed=3)
    img[:, 320:] = 0
    f = extract_orb(img, cfg)
    counts = _cell_counts(f, cfg)
    quota = cfg.n_features / (cfg.grid_cols * cfg.grid_rows)
    assert len(f) >= 0.9 * cfg.n_features
    # Cells fully right of the texture border (col 4 starts at x = 320, a corner may sit on it).
    assert counts[:, 5:].sum() == 0
    assert counts[:, :4].min() > quota
    assert counts.max() <= 2.2 * quota, counts


@pytest.mark.parametrize("value", [0, 128])
def test_orb_blank_image_gives_no_features(value: int) -> None:
    """A uniform frame (all zeros or all grey) has no corners: 0 features, no error."""
    f = extract_orb(np.full((480, 640), value, np.uint8))
    assert len(f) == 0
    assert f.descriptors.shape == (0, 32)


def test_orb_tiny_image_gives_no_features() -> None:
    """An image smaller than twice the edge margin cannot hold a keypoint."""
    assert len(extract_orb(np.zeros((20, 30), np.uint8))) == 0


def test_orb_mask_restricts_keypoints() -> None:
    """With a mask covering the top half, every keypoint lies in the top half."""
    img = _textured(seed=4)
    mask = np.zeros_like(img)
    mask[:240] = 255
    f = extract_orb(img, mask=mask)
    assert len(f) > 300
    assert np.all(f.uv[:, 1] < 240.5)


@pytest.mark.parametrize("seed", range(5))
def test_water_fill_meets_target_and_spreads_quota_evenly(seed: int) -> None:
    """Random corner counts per bin: allotments sum to the target, never exceed what a
    bin has, and every bin that could take more sits at the same multiple of its quota
    (up to rounding): unused quota is redistributed in proportion to quota."""
    rng = np.random.default_rng(seed)
    available = rng.integers(0, 40, 384) * (rng.random(384) < 0.7)
    quota = np.repeat(1000 * 0.1667 / (1 - 1.2**-8) * 1.2 ** -np.arange(8.0) / 48, 48)
    alloc = _water_fill(available, quota, 1000)
    assert alloc.sum() == min(1000, available.sum())
    assert np.all((alloc >= 0) & (alloc <= available))
    open_bins = alloc < available
    if open_bins.any():
        lam_low = ((alloc[open_bins] + 1) / quota[open_bins]).min()
        assert np.all(alloc <= lam_low * quota + 1)
    everything = _water_fill(available, quota, int(available.sum()) + 5)
    np.testing.assert_array_equal(everything, available)


def test_orb_rejects_bad_input() -> None:
    """Colour images, float images and mismatched masks are programming errors."""
    with pytest.raises(GeometryError):
        extract_orb(np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(GeometryError):
        extract_orb(np.zeros((480, 640), np.float32))  # type: ignore[arg-type]
    with pytest.raises(GeometryError):
        extract_orb(np.zeros((480, 640), np.uint8), mask=np.zeros((10, 10), np.uint8))
    with pytest.raises(ConfigError):
        OrbConfig(min_fast_threshold=30, fast_threshold=20)


def _opencv_descriptors(img: U8, f: Features, cfg: OrbConfig) -> tuple[NDArray[np.int64], U8]:
    """cv2.ORB's descriptors for the keypoints of ``f`` (the indices cv2 kept, their bits)."""
    orb = cv2.ORB.create(
        nfeatures=cfg.n_features,
        scaleFactor=cfg.scale_factor,
        nlevels=cfg.n_levels,
        edgeThreshold=cfg.edge_margin,
        patchSize=31,
    )
    kps = [
        cv2.KeyPoint(float(u), float(v), float(sz), float(a), float(r), int(o), i)
        for i, ((u, v), sz, a, r, o) in enumerate(
            zip(f.uv, f.size, f.angle_deg, f.response, f.octave, strict=True)
        )
    ]
    kept, desc = orb.compute(img, kps)
    return np.array([k.class_id for k in kept], np.int64), desc


def _frames_for_bits() -> list[U8]:
    frames = [_textured(seed=11), cv2.GaussianBlur(_textured(seed=12), (0, 0), 2.0)]
    frames.append(
        cv2.warpAffine(_textured(seed=13), cv2.getRotationMatrix2D((320, 240), 37.0, 1.0), (640, 480))
    )
    if TUM_RGB.is_dir():  # real frames when ../shared is there (motion blur, low texture)
        for path in sorted(TUM_RGB.glob("*.png"))[::25]:
            frames.append(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2GRAY))
    return frames


@pytest.mark.parametrize("edge_margin", [19, 16])
def test_orb_descriptors_are_opencvs_bits(edge_margin: int) -> None:
    """Our rBRIEF gives, bit for bit, what cv2.ORB.compute gives for the same keypoints
    (the vocabularies were trained on those bits); margin 16 reads cv2's reflected border."""
    cfg = OrbConfig(edge_margin=edge_margin)
    ex = OrbExtractor(cfg)
    n_checked = 0
    for img in _frames_for_bits():
        f = ex.extract(img)
        assert len(f) > 300
        kept, desc = _opencv_descriptors(img, f, cfg)
        np.testing.assert_array_equal(np.sort(kept), np.arange(len(f)))
        np.testing.assert_array_equal(f.descriptors[kept], desc)
        n_checked += len(f)
    assert n_checked > 1500
    assert set(np.unique(f.octave)) == set(range(cfg.n_levels))


def test_orb_descriptors_match_across_rotation() -> None:
    """Rotating the frame by 30 degrees: ORB (oriented, rBRIEF) still matches correctly.

    Checks orientation and descriptors end to end: mutual ratio-test matches must map
    through the known rotation within 3 px for most pairs.
    """
    img = _textured(seed=5)
    M = cv2.getRotationMatrix2D((319.5, 239.5), 30.0, 1.0)
    rot = cv2.warpAffine(img, M, (640, 480), flags=cv2.INTER_LINEAR, borderValue=0)
    ex = OrbExtractor()
    a, b = ex.extract(img), ex.extract(rot)
    m = match_descriptors(a.descriptors, b.descriptors, ratio=0.8, cross_check=True)
    assert m.query_idx.size > 150
    pred = a.uv[m.query_idx] @ M[:, :2].T + M[:, 2]
    err = np.linalg.norm(pred - b.uv[m.train_idx], axis=1)
    assert np.mean(err < 3.0) > 0.85


# --------------------------------------------------------------------------- SIFT / thermal


def _thermal_like(amplitude: float, seed: int = 7) -> U8:
    """388x284 uint8 frame: small shapes of ``amplitude`` grey levels on 60, blurred (sigma 1)."""
    img = 60.0 + amplitude * _shapes(284, 388, 1500, seed, small=True)
    return np.clip(cv2.GaussianBlur(img, (0, 0), 1.0), 0, 255).astype(np.uint8)


def test_sift_rich_image_keeps_initial_threshold() -> None:
    """High-contrast texture: >= 800 points at once, so the threshold stays at 0.04."""
    cfg = SiftConfig()
    f, c = extract_sift_adaptive(_thermal_like(255.0), cfg)
    assert c == pytest.approx(cfg.initial_contrast)
    assert cfg.min_features <= len(f) <= cfg.max_features
    assert f.kind == "sift" and f.descriptors.dtype == np.float32 and f.descriptors.shape == (len(f), 128)


def test_sift_low_contrast_lowers_threshold_in_steps_until_enough() -> None:
    """Low-contrast blurred frame (paper 003 Sec. IV-C): threshold drops by 0.005 steps.

    It stops at the first threshold giving >= 800 points: one step higher gives fewer.
    """
    cfg = SiftConfig()
    img = _thermal_like(30.0)
    f, c = extract_sift_adaptive(img, cfg)
    steps = (cfg.initial_contrast - c) / cfg.contrast_step
    assert steps >= 1 and abs(steps - round(steps)) < 1e-6
    assert c > cfg.min_contrast and len(f) >= cfg.min_features
    above = c + cfg.contrast_step
    g, c_above = extract_sift_adaptive(img, SiftConfig(initial_contrast=above, min_contrast=above))
    assert c_above == pytest.approx(above) and len(g) < cfg.min_features


def test_sift_loop_is_bounded_by_min_contrast() -> None:
    """Almost no contrast: the loop ends at min_contrast with what it found, no error."""
    cfg = SiftConfig()
    f, c = extract_sift_adaptive(_thermal_like(2.0), cfg)
    assert c == pytest.approx(cfg.min_contrast)
    assert len(f) < cfg.min_features
    blank, c_blank = extract_sift_adaptive(np.zeros((284, 388), np.uint8), cfg)
    assert len(blank) == 0 and c_blank == pytest.approx(cfg.min_contrast)


def test_sift_starts_from_given_threshold() -> None:
    """start_contrast (the previous frame's threshold) is the first one tried."""
    f, c = extract_sift_adaptive(_thermal_like(255.0), SiftConfig(), start_contrast=0.02)
    assert c == pytest.approx(0.02) and len(f) >= 800


def test_thermal_to_gray8_stretches_robustly() -> None:
    """Kelvin frame with hot outliers and NaN: 1-99 % range spans 0..255, NaN -> 0."""
    rng = np.random.default_rng(0)
    t = (295.0 + rng.normal(0.0, 0.5, (284, 388))).astype(np.float32)
    t[0, :10] = 1000.0  # a few saturated hot pixels must not squash the rest
    t[1, :5] = np.nan
    g = thermal_to_gray8(t, clahe_clip=None)
    assert g.dtype == np.uint8 and g.shape == t.shape
    assert np.percentile(g, 5) < 40 and np.percentile(g, 95) > 215
    assert np.all(g[1, :5] == 0)
    assert thermal_to_gray8(t).dtype == np.uint8  # with CLAHE
    assert np.all(thermal_to_gray8(np.full((10, 10), 300.0, np.float32)) == 0)
    assert np.all(thermal_to_gray8(np.full((10, 10), np.nan, np.float32)) == 0)


# --------------------------------------------------------------------------- matching


def test_match_descriptors_hamming_ratio_and_cross_check() -> None:
    """Shuffled copies with 8 flipped bits plus random distractors: the permutation comes back."""
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    perm = rng.permutation(400)
    b = np.concatenate([_flip_bits(a[perm], 8, rng), rng.integers(0, 256, (200, 32), dtype=np.uint8)])
    truth = np.empty(400, np.int64)
    truth[perm] = np.arange(400)  # a[i] sits at b[truth[i]]
    for cross in (False, True):
        m = match_descriptors(a, b, ratio=0.8, cross_check=cross)
        assert m.query_idx.size >= 395
        np.testing.assert_array_equal(m.train_idx, truth[m.query_idx])
        assert np.all(m.distance <= 8)
    m = match_descriptors(a, b, cross_check=True)
    assert np.unique(m.train_idx).size == m.train_idx.size


def test_match_descriptors_l2_for_sift_and_empty_sets() -> None:
    """float32 descriptors use L2; an empty side gives no matches; mixed dtypes are rejected."""
    rng = np.random.default_rng(2)
    a = rng.random((50, 128)).astype(np.float32)
    b = (a + rng.normal(0, 0.01, a.shape)).astype(np.float32)
    m = match_descriptors(a, b)
    np.testing.assert_array_equal(m.query_idx, m.train_idx)
    assert m.query_idx.size == 50
    assert match_descriptors(a, np.zeros((0, 128), np.float32)).query_idx.size == 0
    with pytest.raises(GeometryError):
        match_descriptors(a, rng.integers(0, 256, (5, 32), dtype=np.uint8))


def test_match_projected_recovers_known_correspondences_one_to_one() -> None:
    """1500 map points, 900 seen in a 1000-feature frame (moved <= 2 px, 6 bits flipped).

    The 100 extra frame features are decoys next to true ones with 40 flipped bits;
    600 map points project elsewhere or are invisible (NaN). At least 95 % of the 900
    must come back right, no wrong pairs beyond 2 %, and the result is one-to-one.
    """
    rng = np.random.default_rng(3)
    m_pts, seen = 1500, 900
    map_desc = rng.integers(0, 256, (m_pts, 32), dtype=np.uint8)
    map_uv = np.column_stack([rng.uniform(10, 630, m_pts), rng.uniform(10, 470, m_pts)])
    vis = rng.permutation(m_pts)[:seen]
    frame_uv = map_uv[vis] + rng.uniform(-1.4, 1.4, (seen, 2))
    frame_desc = _flip_bits(map_desc[vis], 6, rng)
    decoy_src = rng.choice(seen, 100, replace=False)
    decoy_uv = frame_uv[decoy_src] + rng.uniform(-3, 3, (100, 2))
    decoy_desc = _flip_bits(frame_desc[decoy_src], 40, rng)
    order = rng.permutation(seen + 100)
    all_uv = np.concatenate([frame_uv, decoy_uv])[order]
    all_desc = np.concatenate([frame_desc, decoy_desc])[order]
    frame = _orb_features(all_uv, all_desc)
    truth_frame_of_map = np.full(m_pts, -1)
    truth_frame_of_map[vis] = np.argsort(order)[:seen]
    pred = map_uv.copy()
    hidden = np.setdiff1d(np.arange(m_pts), vis)
    pred[hidden[:300]] = np.nan
    pred[hidden[300:]] = rng.uniform(0, 640, (hidden.size - 300, 2))

    mi, fi = match_projected(map_desc, pred, frame, radius_px=8.0)
    assert np.unique(fi).size == fi.size and np.unique(mi).size == mi.size
    correct = truth_frame_of_map[mi] == fi
    assert correct.sum() >= 0.95 * seen
    assert (~correct).sum() <= 0.02 * seen


def test_match_projected_radius_octave_and_distance_gates() -> None:
    """Outside the radius, over max_hamming or at a far octave: no match; ties resolved by distance."""
    rng = np.random.default_rng(4)
    d = rng.integers(0, 256, (2, 32), dtype=np.uint8)
    frame = _orb_features(np.array([[100.0, 100.0], [300.0, 300.0]]), d, octave=np.array([0, 5]))
    far = np.array([[120.0, 100.0], [300.0, 300.0]])
    mi, fi = match_projected(d, far, frame, radius_px=10.0)
    assert mi.tolist() == [1] and fi.tolist() == [1]
    mi, _ = match_projected(d, far, frame, radius_px=10.0, map_octave_pred=np.array([0, 0]))
    assert mi.size == 0
    noisy = _flip_bits(d, 60, rng)
    mi, _ = match_projected(noisy, frame.uv.astype(np.float64), frame, radius_px=5.0, max_hamming=50)
    assert mi.size == 0
    # Two map points on one feature: the closer descriptor wins it.
    two = np.stack([_flip_bits(d[:1], 10, rng)[0], _flip_bits(d[:1], 3, rng)[0]])
    mi, fi = match_projected(two, np.array([[101.0, 100.0], [99.0, 100.0]]), frame, radius_px=5.0)
    assert mi.tolist() == [1] and fi.tolist() == [0]
    empty = _orb_features(np.zeros((0, 2)), np.zeros((0, 32), np.uint8))
    assert match_projected(d, far, empty, radius_px=5.0)[0].size == 0
