"""Random-fern keyframe codes (paper 003 Eq. 10-11, Glocker et al. 2015) and their index."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from wardmap.server.backend.places import (
    FernConfig,
    FernEncoder,
    FernIndex,
    _uniform,
    block_similarity,
)
from wardmap.shared.errors import ConfigError, GeometryError

H, W = 480, 640


def _scene(rng: np.random.Generator, width: int = W) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random colour image (BGR uint8 (H, width, 3)) and depth (float32, 0.8-4.5 m)."""
    coarse = rng.uniform(0, 255, (12, width // 40, 3)).astype(np.float32)
    fine = rng.normal(0, 25, (48, width // 10, 3)).astype(np.float32)
    img = np.asarray(cv2.resize(coarse, (width, H), interpolation=cv2.INTER_CUBIC), np.float32)
    img += np.asarray(cv2.resize(fine, (width, H), interpolation=cv2.INTER_CUBIC), np.float32)
    depth = cv2.resize(rng.uniform(0.8, 4.5, (6, width // 80)).astype(np.float32), (width, H))
    return np.clip(img, 0, 255).astype(np.uint8), depth.astype(np.float32)


def test_splitmix64_reference_value() -> None:
    """The fern generator is SplitMix64: seeded with 0 its first output is 0xE220A8397B1DCDAF,
    so fern layouts cannot change with a NumPy release."""
    assert _uniform(0, 1)[0] == (0xE220A8397B1DCDAF >> 11) * 2.0**-53
    u = _uniform(5, 10000)
    assert u.min() >= 0 and u.max() < 1 and abs(u.mean() - 0.5) < 0.01


def test_codes_are_deterministic_per_seed() -> None:
    """Two encoders with one seed give identical codes; another seed gives unrelated codes."""
    img, depth = _scene(np.random.default_rng(1))
    a = FernEncoder(FernConfig(seed=11)).encode(img, depth)
    b = FernEncoder(FernConfig(seed=11)).encode(img, depth)
    c = FernEncoder(FernConfig(seed=12)).encode(img, depth)
    assert a.dtype == np.uint8 and a.shape == (500,)
    np.testing.assert_array_equal(a, b)
    assert block_similarity(a, c) < 0.5


def test_codes_follow_eq_11() -> None:
    """Bit i of block k is [I(c_i, x_k) >= tau_ki] on the small blurred image; ferns of a block
    read R, G, B, D in turn; thresholds lie in each channel's range."""
    cfg = FernConfig(blocks=300, ferns_per_block=6)
    enc = FernEncoder(cfg)
    img, depth = _scene(np.random.default_rng(2))
    chans = enc.image_channels(img, depth)
    assert chans.shape == (cfg.height, cfg.width, 4)
    xy, ch, tau = enc.fern_pixels, enc.fern_channels, enc.fern_thresholds
    np.testing.assert_array_equal(ch[0], [0, 1, 2, 3, 0, 1])
    colour = ch != 3
    assert tau[colour].min() >= 0 and tau[colour].max() < 255
    assert tau[~colour].min() >= 0.8 and tau[~colour].max() < 4.0
    assert xy[:, 0].max() < cfg.width and xy[:, 1].max() < cfg.height
    values = chans[xy[:, 1, None], xy[:, 0, None], ch]
    expected = ((values >= tau) * (1 << np.arange(6))).sum(axis=1)
    np.testing.assert_array_equal(enc.encode(img, depth), expected)


def test_same_image_similarity_one_and_small_changes_keep_it_high() -> None:
    """Encoding twice gives similarity 1; +8 grey levels or sensor noise keep it above 0.8."""
    rng = np.random.default_rng(3)
    enc = FernEncoder()
    img, depth = _scene(rng)
    codes = enc.encode(img, depth)
    assert block_similarity(codes, enc.encode(img.copy(), depth.copy())) == 1.0
    brighter = np.clip(img.astype(np.int16) + 8, 0, 255).astype(np.uint8)
    assert block_similarity(codes, enc.encode(brighter, depth)) > 0.8
    noisy = np.clip(img + rng.normal(0, 5, img.shape), 0, 255).astype(np.uint8)
    noisy_depth = (depth * (1 + rng.normal(0, 0.01, depth.shape))).astype(np.float32)
    assert block_similarity(codes, enc.encode(noisy, noisy_depth)) > 0.9


def test_unrelated_images_score_low() -> None:
    """Twenty pairs of independent scenes share well under the 0.8 of a re-observation: on a
    blurred image many thresholds fall outside the local colour range, so chance agreement
    is about 0.4."""
    rng = np.random.default_rng(4)
    enc = FernEncoder()
    sims = [block_similarity(enc.encode(*_scene(rng)), enc.encode(*_scene(rng))) for _ in range(20)]
    assert np.mean(sims) < 0.45 and max(sims) < 0.55


def test_shift_lowers_similarity_gradually() -> None:
    """Panning over a wider scene: similarity falls with the shift, a few pixels cost little."""
    img, depth = _scene(np.random.default_rng(5), width=W + 256)
    enc = FernEncoder()
    ref = enc.encode(img[:, :W], depth[:, :W])
    shifts = [0, 4, 8, 16, 32, 64, 128, 256]
    sims = [block_similarity(ref, enc.encode(img[:, s : s + W], depth[:, s : s + W])) for s in shifts]
    assert sims[0] == 1.0 and sims[1] > 0.85
    assert all(b <= a + 0.02 for a, b in itertools.pairwise(sims))
    assert sims[-1] < sims[3] - 0.3


def _bits(codes: np.ndarray) -> np.ndarray:
    """(m, 4) fern bits of 4-bit block codes."""
    return (codes[:, None] >> np.arange(4)) & 1


def test_depth_holes() -> None:
    """Scattered missing pixels and NaN are filled from their neighbours. An image without any
    depth is encoded deterministically, and unrelated depth-less images agree on the depth
    fern's bit no more often than on a colour fern's: holes are neither near nor far (a fixed
    value would make every hole agree)."""
    rng = np.random.default_rng(6)
    enc = FernEncoder()
    img, depth = _scene(rng)
    full = enc.encode(img, depth)
    speckled = np.where(rng.random(depth.shape) < 0.2, 0.0, depth).astype(np.float32)
    assert block_similarity(full, enc.encode(img, speckled)) > 0.95
    nan_holes = np.where(speckled == 0, np.nan, speckled).astype(np.float32)
    np.testing.assert_array_equal(enc.encode(img, nan_holes), enc.encode(img, speckled))

    none = np.zeros_like(depth)
    blind = enc.encode(img, none)
    np.testing.assert_array_equal(blind, enc.encode(img, none))
    assert 0.3 < block_similarity(full, blind) < 1.0  # colour bits still match

    agree = np.mean(
        [
            (_bits(enc.encode(_scene(rng)[0], none)) == _bits(enc.encode(_scene(rng)[0], none))).mean(axis=0)
            for _ in range(20)
        ],
        axis=0,
    )  # per fern slot: R, G, B, D-on-hole
    assert agree[3] < 0.9
    assert agree[3] <= agree[:3].max() + 0.03


def test_hole_ferns_read_their_colour_pixel() -> None:
    """On a hole, a depth fern compares the block's hole pixel and channel, mapped from 0..255
    onto the depth range, with its threshold."""
    cfg = FernConfig(blocks=200)
    enc = FernEncoder(cfg)
    img, depth = _scene(np.random.default_rng(12))
    depth[:, : W // 2] = 0.0  # left half without depth
    chans = enc.image_channels(img, depth)
    assert np.isnan(chans[:, :10, 3]).all() and np.isfinite(chans[:, -10:, 3]).all()
    xy, hole, tau = enc.fern_pixels, enc.fern_hole_pixels, enc.fern_thresholds
    d = chans[xy[:, 1], xy[:, 0], 3]
    alt = chans[hole[:, 1], hole[:, 0], hole[:, 2]] * (3.2 / 255.0) + 0.8
    d_bit = np.where(np.isnan(d), alt, d) >= tau[:, 3]
    assert np.isnan(d).any() and np.isfinite(d).any()
    np.testing.assert_array_equal(_bits(enc.encode(img, depth))[:, 3], d_bit)


def test_depth_of_another_size_is_resampled() -> None:
    """Depth at half the colour resolution encodes like the full-size depth."""
    img, depth = _scene(np.random.default_rng(7))
    enc = FernEncoder()
    half = cv2.resize(depth, (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    assert block_similarity(enc.encode(img, depth), enc.encode(img, half)) > 0.97


def test_encoder_rejects_bad_arrays() -> None:
    """Wrong dtype or shape raises GeometryError."""
    enc = FernEncoder()
    img, depth = _scene(np.random.default_rng(8))
    with pytest.raises(GeometryError, match="bgr"):
        enc.encode(img.astype(np.float32), depth)
    with pytest.raises(GeometryError, match="bgr"):
        enc.encode(img[:, :, 0], depth)
    with pytest.raises(GeometryError, match="depth"):
        enc.encode(img, depth[None])
    with pytest.raises(GeometryError, match="depth"):
        enc.encode(img, (depth * 1000).astype(np.uint16))


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("blocks", 0),
        ("ferns_per_block", 9),
        ("width", 0),
        ("blur_sigma_px", -1.0),
        ("depth_range_m", (4.0, 0.8)),
        ("depth_min_coverage", 0.0),
        ("seed", -1),
    ],
)
def test_config_rejects_bad_values(field: str, value: object) -> None:
    """Out-of-range settings raise ConfigError naming the field."""
    with pytest.raises(ConfigError, match=field):
        FernConfig(**{field: value})


def test_query_ranks_the_true_keyframe_first() -> None:
    """Among 200 unrelated keyframes, a re-observation (brighter, noisy) of keyframe 57 ranks
    first; the mask can hide it; results are sorted by similarity."""
    rng = np.random.default_rng(9)
    enc = FernEncoder()
    index = FernIndex(enc.config.blocks)
    scenes = [_scene(rng) for _ in range(200)]
    for node, (img, depth) in enumerate(scenes):
        index.add(1000 + node, enc.encode(img, depth))
    img, depth = scenes[57]
    again = np.clip(img.astype(np.float64) + 6 + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    q = enc.encode(again, depth)
    best = index.query(q, 5)
    assert best[0][0] == 1057 and best[0][1] > 0.8
    assert best[1][1] < best[0][1] - 0.25
    assert [s for _, s in best] == sorted((s for _, s in best), reverse=True)

    allowed = index.nodes() != 1057
    hidden = index.query(q, 5, allowed)
    assert len(hidden) == 5 and all(n != 1057 for n, _ in hidden)
    assert hidden[0] == best[1]
    assert index.query(q, 5, np.zeros(len(index), bool)) == []


def test_ties_broken_by_node_id_and_k_bounds() -> None:
    """Equal codes rank by ascending node id; k larger than the index returns every row;
    k <= 0 returns nothing."""
    index = FernIndex(8)
    a = np.arange(8, dtype=np.uint8)
    for node in (9, 3, 5):
        index.add(node, a)
    index.add(1, np.array([0, 1, 2, 3, 0, 0, 0, 0], np.uint8))
    assert index.query(a, 3) == [(3, 1.0), (5, 1.0), (9, 1.0)]
    assert index.query(a, 2) == [(3, 1.0), (5, 1.0)]
    assert index.query(a, 10) == [(3, 1.0), (5, 1.0), (9, 1.0), (1, 0.5)]
    assert index.query(a, 0) == []
    assert index.query(a, 1, np.array([True, False, False, True])) == [(9, 1.0)]


def test_index_grows_and_keeps_rows() -> None:
    """Past its initial capacity the index doubles; rows, ids and codes survive, in add order."""
    rng = np.random.default_rng(10)
    index = FernIndex(50, initial_capacity=4)
    codes = rng.integers(0, 16, (100, 50), dtype=np.uint8)
    ids = rng.permutation(10_000)[:100]
    for node, c in zip(ids, codes, strict=True):
        index.add(int(node), c)
    assert len(index) == 100
    np.testing.assert_array_equal(index.nodes(), ids)
    for row in (0, 3, 4, 63, 99):
        np.testing.assert_array_equal(index.codes(int(ids[row])), codes[row])
        assert index.query(codes[row], 1)[0] == (int(ids[row]), 1.0)
    with pytest.raises(KeyError):
        index.codes(10_001)


def test_index_memory_is_about_m_bytes_per_keyframe() -> None:
    """1000 keyframes of 500 blocks take about 500 bytes each (plus the id, at most 2x slack)."""
    index = FernIndex(500)
    rng = np.random.default_rng(11)
    for node in range(1000):
        index.add(node, rng.integers(0, 16, 500, dtype=np.uint8))
    assert 1000 * 500 <= index.nbytes <= 2 * 1000 * (500 + 8) + 100_000


def test_index_rejects_bad_input() -> None:
    """Codes of the wrong size or dtype, a wrong mask and a duplicate node are refused."""
    index = FernIndex(8)
    index.add(1, np.zeros(8, np.uint8))
    with pytest.raises(GeometryError):
        index.add(2, np.zeros(7, np.uint8))
    with pytest.raises(GeometryError):
        index.add(2, np.zeros(8, np.int64))
    with pytest.raises(ValueError, match="already"):
        index.add(1, np.zeros(8, np.uint8))
    with pytest.raises(GeometryError, match="allowed"):
        index.query(np.zeros(8, np.uint8), 1, np.ones(2, bool))
    with pytest.raises(GeometryError, match="allowed"):
        index.query(np.zeros(8, np.uint8), 1, np.ones(1, np.int64))
