"""Place recognition by randomised ferns (paper 003 Eq. 10-11; Glocker et al. 2015).

A keyframe is reduced to ``m`` block codes. Each block ``k`` holds ``n`` binary ferns
(Eq. 10, ``C = {block_k}_{k=1..m}``, ``block = {fern_i}_{i=1..n}``); fern ``i`` compares one
channel ``c`` of the small, blurred RGB-D image at the block's pixel ``x`` with a threshold
``tau`` (Eq. 11, ``f(I, theta, tau) = [I(theta) >= tau]``, ``theta = {c, x}``). The ``n``
bits of a block form its code, an integer in ``[0, 2^n)`` stored as one byte: bit ``i`` is
fern ``i``. As in the paper's Table 1 (a 4-bit code over R, G, B, D), the ferns of a block
share its pixel and take the channels R, G, B, D in turn (fern ``i`` reads channel
``i mod 4``).

Two keyframes are compared by the block-wise Hamming distance of Glocker et al.,
``BlockHD(C_a, C_b) = (1/m) * sum_k [code_a_k != code_b_k]``; similarity is ``1 - BlockHD``,
the fraction of blocks whose codes are equal.

Pixel positions and thresholds are drawn once from ``FernConfig.seed`` with a SplitMix64
counter generator written out here, so the codes of a keyframe are the same in every
process, on every restart and under every NumPy release (stored codes stay comparable).

Missing depth: small holes are filled by normalised convolution (depth and validity are
downsampled and blurred separately, then divided). A pixel that still has too little
measured depth around it (valid weight below ``depth_min_coverage``) is a hole. On a hole a
depth fern turns into a colour fern: it reads one colour channel at a second pixel of its
block (both drawn with the ferns) against its threshold mapped linearly from
``depth_range_m`` onto 0..255. A hole is then neither near nor far, and the replacement bit
is not a copy of the block's own colour bits: two unrelated images with holes at the same
place agree on it as often as on any colour fern, not always.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.shared.errors import ConfigError, GeometryError

__all__ = ["FernConfig", "FernEncoder", "FernIndex", "block_similarity"]

F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]
I64 = NDArray[np.int64]

_CHANNELS = 4
"""R, G, B, D: fern ``i`` of a block reads channel ``i % 4``."""
_DEPTH = 3
_MASK64 = (1 << 64) - 1


@dataclass(frozen=True)
class FernConfig:
    """Parameters of the fern encoding (Eq. 10-11)."""

    blocks: int = 500
    """m: blocks per keyframe; one byte each in the index."""
    ferns_per_block: int = 4
    """n: ferns (bits) per block, 1..8; 4 gives one bit for each of R, G, B, D (paper 003 Table 1)."""
    width: int = 80
    """Width of the downsampled image the ferns read, pixels."""
    height: int = 60
    """Height of the downsampled image the ferns read, pixels."""
    blur_sigma_px: float = 2.5
    """Gaussian blur of the downsampled image (its pixels); 0 = none. Trades discrimination for
    tolerance to a small change of viewpoint (Glocker et al. blur their 40 x 30 image with 2.5)."""
    depth_range_m: tuple[float, float] = (0.8, 4.0)
    """Depth thresholds tau are uniform in this range, metres."""
    depth_min_coverage: float = 0.25
    """A downsampled pixel has depth when at least this (blur-weighted) share of the pixels
    around it measured depth; otherwise it is a hole (see the module docstring)."""
    seed: int = 37
    """Seed of the fern positions and thresholds, 0 <= seed < 2^64; fixed for a map's lifetime."""

    def __post_init__(self) -> None:
        if not isinstance(self.blocks, int) or self.blocks < 1:
            raise ConfigError(f"places.blocks must be an integer >= 1, got {self.blocks!r}")
        if not isinstance(self.ferns_per_block, int) or not 1 <= self.ferns_per_block <= 7:
            raise ConfigError(
                "places.ferns_per_block must be an integer in 1..7 (code 255 marks a keyframe without "
                f"one), got {self.ferns_per_block!r}"
            )
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, int) or not 1 <= v <= 4096:
                raise ConfigError(f"places.{name} must be an integer in 1..4096, got {v!r}")
        if not np.isfinite(self.blur_sigma_px) or self.blur_sigma_px < 0:
            raise ConfigError(f"places.blur_sigma_px must be >= 0, got {self.blur_sigma_px!r}")
        if len(self.depth_range_m) != 2:
            raise ConfigError(f"places.depth_range_m needs two values, got {self.depth_range_m!r}")
        lo, hi = (float(v) for v in self.depth_range_m)
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
            raise ConfigError(f"places.depth_range_m needs 0 < min < max, got {self.depth_range_m!r}")
        if not 0 < self.depth_min_coverage <= 1:
            raise ConfigError(f"places.depth_min_coverage must be in (0, 1], got {self.depth_min_coverage!r}")
        if not isinstance(self.seed, int) or not 0 <= self.seed <= _MASK64:
            raise ConfigError(f"places.seed must be an integer in [0, 2^64), got {self.seed!r}")


def _uniform(seed: int, count: int) -> NDArray[np.float64]:
    """``count`` uniform floats in [0, 1) from SplitMix64 (Steele et al. 2014) seeded by ``seed``.

    Written out (not ``numpy.random``) so the stream is fixed forever.
    """
    with np.errstate(over="ignore"):
        z = np.uint64(seed) + np.uint64(0x9E3779B97F4A7C15) * np.arange(1, count + 1, dtype=np.uint64)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) * 2.0**-53


class FernEncoder:
    """Block codes of keyframes (Eq. 10-11); stateless after construction.

    The ferns are drawn in the constructor from ``config.seed``: block ``k`` sits at pixel
    ``(x_k, y_k)``, uniform over the ``width x height`` image; fern ``i`` of block ``k`` reads
    channel ``i % 4`` (R, G, B, D) against a threshold uniform in [0, 255) for colour and in
    ``depth_range_m`` for depth.
    """

    def __init__(self, config: FernConfig | None = None) -> None:
        self.config = config if config is not None else FernConfig()
        c = self.config
        m, n = c.blocks, c.ferns_per_block
        u = _uniform(c.seed, 5 * m + m * n)
        x, y, hx, hy = (
            np.minimum((u[j * m : (j + 1) * m] * size).astype(np.int64), size - 1)
            for j, size in enumerate((c.width, c.height, c.width, c.height))
        )
        self._pixel: I64 = y * c.width + x  # (m,) flat index into the small image
        self._hole_pixel: I64 = hy * c.width + hx  # (m,) where a depth fern on a hole reads colour
        self._hole_channel: I64 = np.minimum((u[4 * m : 5 * m] * 3).astype(np.int64), 2)  # (m,) R, G or B
        self._channel: I64 = np.tile(np.arange(n, dtype=np.int64) % _CHANNELS, (m, 1))  # (m, n)
        lo, hi = (float(v) for v in c.depth_range_m)
        t = u[5 * m :].reshape(m, n)
        tau = np.where(self._channel == _DEPTH, lo + t * (hi - lo), t * 255.0)
        self._tau: F32 = tau.astype(np.float32)  # (m, n)
        self._weights = (1 << np.arange(n, dtype=np.uint8)).astype(np.uint8)  # bit i = fern i

    @property
    def fern_pixels(self) -> I64:
        """(m, 2) int64 pixel ``(x, y)`` of each block in the ``width x height`` image."""
        w = self.config.width
        return np.column_stack([self._pixel % w, self._pixel // w])

    @property
    def fern_hole_pixels(self) -> I64:
        """(m, 3) int64 ``(x, y, channel)``: the pixel and colour channel (0 R, 1 G, 2 B) a
        block's depth ferns read on a hole."""
        w = self.config.width
        return np.column_stack([self._hole_pixel % w, self._hole_pixel // w, self._hole_channel])

    @property
    def fern_channels(self) -> I64:
        """(m, n) int64 channel of each fern: 0 R, 1 G, 2 B, 3 D."""
        return self._channel.copy()

    @property
    def fern_thresholds(self) -> F32:
        """(m, n) float32 threshold tau of each fern (0..255 colour, metres depth)."""
        return self._tau.copy()

    def _small(self, img: U8 | F32) -> F32:
        """Area-downsample to ``width x height``, then blur (float32 out)."""
        c = self.config
        small = np.asarray(cv2.resize(img, (c.width, c.height), interpolation=cv2.INTER_AREA), np.float32)
        if c.blur_sigma_px > 0:
            small = np.asarray(cv2.GaussianBlur(small, (0, 0), c.blur_sigma_px), np.float32)
        return small

    def image_channels(self, bgr: U8, depth_m: NDArray[np.floating]) -> F32:
        """The (height, width, 4) R, G, B, D image the ferns read: colour 0..255 (float32),
        depth in metres, NaN on holes (pixels without enough measured depth nearby)."""
        img = np.asarray(bgr)
        if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3 or 0 in img.shape:
            raise GeometryError(f"fern encode: expected bgr uint8 (H, W, 3), got {img.dtype} {img.shape}")
        d = np.asarray(depth_m)
        if d.ndim != 2 or 0 in d.shape or not np.issubdtype(d.dtype, np.floating):
            raise GeometryError(f"fern encode: expected depth_m float (h, w), got {d.dtype} {d.shape}")
        c = self.config
        colour = self._small(img)[:, :, ::-1]  # (h, w, 3) R, G, B
        valid = (d > 0) & (d < np.inf)  # NaN compares False
        d0 = np.where(valid, d, 0.0).astype(np.float32)
        weight = self._small(valid.astype(np.float32))
        depth_sum = self._small(d0)
        has_depth = weight >= c.depth_min_coverage
        depth = np.where(has_depth, depth_sum / np.where(has_depth, weight, 1.0), np.nan)
        return np.concatenate([colour, depth[:, :, None]], axis=2).astype(np.float32)

    def encode(self, bgr: U8, depth_m: NDArray[np.floating]) -> U8:
        """Block codes (m,) uint8 of one keyframe (Eq. 10-11).

        Args:
            bgr: colour image, uint8 (H, W, 3), OpenCV's B, G, R order.
            depth_m: depth registered to the colour camera, float (h, w) metres, any size
                (resampled to the fern image); 0 or non-finite = no measurement.

        Returns:
            uint8 (m,): code of block k, bit i = ``I(c_i, x_k) >= tau_ki`` (Eq. 11).

        Raises:
            GeometryError: wrong dtype or shape.
        """
        flat = self.image_channels(bgr, depth_m).reshape(-1, _CHANNELS)
        values = flat[self._pixel[:, None], self._channel]  # (m, n)
        hole = np.isnan(values)
        if hole.any():  # the block's hole colour, mapped from 0..255 onto the depth range
            lo, hi = (float(v) for v in self.config.depth_range_m)
            alt = flat[self._hole_pixel, self._hole_channel] * ((hi - lo) / 255.0) + lo  # (m,)
            values = np.where(hole, alt[:, None], values)
        bits = (values >= self._tau).astype(np.uint8)
        codes: U8 = (bits * self._weights).sum(axis=1, dtype=np.uint8)
        return codes


def block_similarity(codes_a: U8, codes_b: U8) -> float:
    """``1 - BlockHD``: the fraction of blocks whose codes are equal (Glocker et al. 2015)."""
    a, b = np.asarray(codes_a), np.asarray(codes_b)
    if a.ndim != 1 or a.shape != b.shape or a.size == 0:
        raise GeometryError(
            f"block_similarity: expected two equal (m,) code vectors, got {a.shape}, {b.shape}"
        )
    return float(np.count_nonzero(a == b)) / a.size


class FernIndex:
    """Block codes of many keyframes in one (N, m) uint8 matrix, queried by similarity.

    Rows are kept in add order (``nodes()[row]`` is the row's node id); the matrix doubles
    when full. One owner; not thread-safe.
    """

    def __init__(self, blocks: int, *, initial_capacity: int = 256) -> None:
        if blocks < 1:
            raise ConfigError(f"places.blocks must be >= 1, got {blocks}")
        if initial_capacity < 1:
            raise ConfigError(f"fern index: initial_capacity must be >= 1, got {initial_capacity}")
        self.blocks = int(blocks)
        self._codes: U8 = np.zeros((initial_capacity, self.blocks), np.uint8)
        self._nodes: I64 = np.zeros(initial_capacity, np.int64)
        self._row: dict[int, int] = {}
        self._n = 0

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Memory held by the index in bytes: the allocated code matrix and node ids plus the
        id-to-row table (``sys.getsizeof``, the table itself)."""
        return int(self._codes.nbytes + self._nodes.nbytes + sys.getsizeof(self._row))

    def _check_codes(self, codes: U8, fn: str) -> U8:
        c = np.asarray(codes)
        if c.dtype != np.uint8 or c.shape != (self.blocks,):
            raise GeometryError(
                f"fern index {fn}: expected codes uint8 ({self.blocks},), got {c.dtype} {c.shape}"
            )
        return c

    def add(self, node: int, codes: U8) -> None:
        """Append keyframe ``node``'s codes (m,) uint8 as the next row.

        Raises:
            GeometryError: codes of the wrong dtype or shape.
            ValueError: ``node`` is already in the index.
        """
        c = self._check_codes(codes, "add")
        node = int(node)
        if node in self._row:
            raise ValueError(f"fern index: node {node} is already indexed")
        if self._n == self._codes.shape[0]:
            cap = 2 * self._codes.shape[0]
            grown = np.zeros((cap, self.blocks), np.uint8)
            grown[: self._n] = self._codes[: self._n]
            nodes = np.zeros(cap, np.int64)
            nodes[: self._n] = self._nodes[: self._n]
            self._codes, self._nodes = grown, nodes
        self._codes[self._n] = c
        self._nodes[self._n] = node
        self._row[node] = self._n
        self._n += 1

    def nodes(self) -> I64:
        """Node ids (N,) int64 in row (add) order; a copy."""
        return self._nodes[: self._n].copy()

    def codes(self, node: int) -> U8:
        """Codes (m,) uint8 of ``node`` (a copy). Raises KeyError for an unknown node."""
        return self._codes[self._row[int(node)]].copy()

    def query(self, codes: U8, k: int, allowed: NDArray[np.bool_] | None = None) -> list[tuple[int, float]]:
        """The ``k`` most similar keyframes: ``[(node, similarity), ...]``.

        Similarity is ``1 - BlockHD`` (fraction of equal block codes, in [0, 1]); the list is
        sorted by similarity descending, ties by node id ascending; it is shorter than ``k``
        when fewer rows are allowed, empty for ``k <= 0``.

        Args:
            codes: the query's codes (m,) uint8.
            k: how many to return.
            allowed: optional bool (N,) over index rows (row order = :meth:`nodes`); only
                True rows are candidates.

        Raises:
            GeometryError: codes or mask of the wrong dtype or shape.
        """
        q = self._check_codes(codes, "query")
        n = self._n
        if allowed is None:
            rows: I64 | None = None
            mat = self._codes[:n]
        else:
            mask = np.asarray(allowed)
            if mask.dtype != np.bool_ or mask.shape != (n,):
                raise GeometryError(
                    f"fern index query: expected allowed bool ({n},), got {mask.dtype} {mask.shape}"
                )
            rows = np.flatnonzero(mask)
            mat = self._codes[rows]
        if k <= 0 or mat.shape[0] == 0:
            return []
        equal = (mat == q).view(np.uint8).sum(axis=1, dtype=np.int32)  # (R,) equal blocks per row
        node_ids = self._nodes[:n] if rows is None else self._nodes[rows]
        if k < equal.shape[0]:
            kth = np.partition(equal, equal.shape[0] - k)[equal.shape[0] - k]
            keep = np.flatnonzero(equal >= kth)  # every row tied with the k-th, then sorted
            equal, node_ids = equal[keep], node_ids[keep]
        order = np.lexsort((node_ids, -equal))[:k]
        m = float(self.blocks)
        return [(int(node_ids[i]), float(equal[i]) / m) for i in order]
