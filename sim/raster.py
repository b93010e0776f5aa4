"""Software z-buffer rasterizer for the simulated hospital (one core, numba).

Renders a triangle soup (:class:`Mesh`) seen by a pinhole camera into depth, instance,
material, colour and texel-luminance images.

Conventions:
    * World frame: metres, z up. ``T_camera_world`` maps world points to the camera
      frame, ``p_cam = T_camera_world @ p_world`` (docs/ARCHITECTURE.md).
    * Camera frame: x right, y down, z forward. Pixel ``(u, v)`` = ``(column, row)``;
      the centre of the top-left pixel is ``(0, 0)``; ``u = fx * x / z + cx``,
      ``v = fy * y / z + cy``. No lens distortion.
    * Texture coordinates are in texels of level 0 of the triangle's texture and wrap
      (repeat) outside ``[0, S)``.

Pipeline (two ``@njit`` passes, single thread, deterministic):
    1. Transform the corners to the camera frame; drop a triangle whose three corners
       lie outside one plane of the view frustum (near, far, four sides).
    2. Per surviving triangle, derive from its *unclipped* 3D corners the screen-space
       planes of ``1/z``, ``s/z`` and ``t/z`` (texture coordinates), so depth and
       texture coordinates are exact and perspective-correct whatever clipping does.
    3. Clip against ``z = near`` (Sutherland-Hodgman; a triangle becomes a polygon of
       up to four corners, i.e. two triangles) and, only when a corner projects more
       than 8192 pixels off screen, against a guard band (keeps integer edge functions
       small). Intersections on an edge are always computed from its inside corner, so
       neighbours sharing the edge get bit-equal points.
    4. Snap corners to 1/256 pixel and rasterize row spans with exact integer edge
       functions and the top-left fill rule: edges shared by two triangles are covered
       exactly once, with no cracks. Depth test: strictly nearer wins (``1/z`` larger,
       i.e. ``z`` strictly less); the first triangle in mesh order wins a tie.
    5. Resolve: one pass over the pixels reads the winning triangle id and shades the
       pixel once (deferred shading: no texture work for hidden surfaces), with a
       per-pixel mip level from the analytic texture-coordinate derivatives and
       trilinear (default) or bilinear filtering, wrap addressing.

Typical use (RGB camera, then the thermal camera from another pose)::

    mips = build_mipmaps(textures)                  # once
    rgb = render(mesh, mips, K_rgb, 640, 480, T_rgb_world)
    th = render(mesh, mips, K_th, 388, 284, T_thermal_world, sample_color=False)
    # th.depth, th.material, th.texel_gray; th.color is None
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.errors import GeometryError
from wardmap.shared.se3 import check_transform

__all__ = [
    "Mesh",
    "MipAtlas",
    "RenderOut",
    "build_mipmaps",
    "render",
]

_SUB = 256  # sub-pixel steps per pixel for snapped corners (8 bits)
_GUARD_PX = 8192.0  # corners projecting further than this outside the image are clipped
_TILE = 4  # textures are stored in 4x4-texel tiles (one cache line of uint32)
_LUMA = (0.299, 0.587, 0.114)  # ITU-R BT.601 luma weights for ``texel_gray``


# --------------------------------------------------------------------------- data types


def _cast_checked(arr: NDArray[Any], dtype: np.dtype[Any], name: str) -> NDArray[Any]:
    """``arr`` as ``dtype``: floats from any real dtype, integers only when every value fits."""
    if dtype.kind == "f":
        if arr.dtype.kind not in "fiu":
            raise GeometryError(f"{name}: expected a real dtype, got {arr.dtype}")
        return arr.astype(dtype)
    if arr.dtype.kind not in "iu":
        raise GeometryError(f"{name}: expected an integer dtype, got {arr.dtype}")
    info = np.iinfo(dtype)
    if arr.size and (int(arr.min()) < info.min or int(arr.max()) > info.max):
        raise GeometryError(f"{name}: values outside [{info.min}, {info.max}] of {dtype}")
    return arr.astype(dtype)


@dataclass(frozen=True, eq=False)
class Mesh:
    """All triangles of the world at one instant, world frame (metres, z up).

    Arrays are converted to the dtypes below (C-contiguous) on construction.

    Attributes:
        vertices: float64 (T, 3, 3), corner ``k`` of triangle ``t`` is
            ``vertices[t, k]`` = (x, y, z) in metres, world frame.
        uv: float32 (T, 3, 2), texture coordinates of each corner in texels of level 0
            of that triangle's texture; values outside ``[0, S)`` repeat.
        texture: int32 (T,), index into the texture atlas.
        instance: uint16 (T,), object instance id; 0 = none (walls, floor).
        material: uint16 (T,), material id (the caller maps it to temperature etc.).
        shade: float32 (T,), precomputed Lambert factor in [0, 1] for the face.
    """

    vertices: NDArray[np.float64]
    uv: NDArray[np.float32]
    texture: NDArray[np.int32]
    instance: NDArray[np.uint16]
    material: NDArray[np.uint16]
    shade: NDArray[np.float32]

    def __post_init__(self) -> None:
        n = np.asarray(self.vertices).shape[0] if np.ndim(self.vertices) else -1
        expected = {
            "vertices": ((n, 3, 3), np.float64),
            "uv": ((n, 3, 2), np.float32),
            "texture": ((n,), np.int32),
            "instance": ((n,), np.uint16),
            "material": ((n,), np.uint16),
            "shade": ((n,), np.float32),
        }
        for name, (shape, dtype) in expected.items():
            arr = np.ascontiguousarray(getattr(self, name))
            if arr.shape != shape:
                raise GeometryError(f"Mesh.{name}: expected shape {shape}, got {arr.shape}")
            if arr.dtype != dtype:
                arr = _cast_checked(arr, np.dtype(dtype), f"Mesh.{name}")
            object.__setattr__(self, name, arr)
        if not np.all(np.isfinite(self.vertices)):
            raise GeometryError("Mesh.vertices: contains non-finite values")
        if not np.all(np.isfinite(self.uv)):
            raise GeometryError("Mesh.uv: contains non-finite values")
        if n and (np.min(self.texture) < 0):
            raise GeometryError("Mesh.texture: negative texture index")

    @property
    def n_triangles(self) -> int:
        """Number of triangles T."""
        return int(self.vertices.shape[0])


@dataclass(frozen=True, eq=False)
class MipAtlas:
    """Textures with their mip pyramids, packed for the rasterizer.

    Attributes:
        texels: uint32 (n_tex, N), every level of every texture. Level ``L`` is stored
            with side ``n = max(size >> L, 4)`` (levels below 4x4 repeated to 4x4) in
            4x4 tiles of 16 words, one 64-byte cache line each, so a bilinear footprint
            rarely spans two lines: texel ``(x, y)`` is at ``offsets[L] +
            (y // 4) * 4 n + (x // 4) * 16 + (y % 4) * 4 + x % 4``. Each word packs
            ``R | G << 8 | B << 16 | Y << 24`` with ``Y`` the BT.601 luma of the texel.
        offsets: int64 (n_levels,), start of each level in ``texels[t]``.
        size: side S of level 0 in texels (a power of two).
    """

    texels: NDArray[np.uint32]
    offsets: NDArray[np.int64]
    size: int

    @property
    def n_textures(self) -> int:
        return int(self.texels.shape[0])

    @property
    def n_levels(self) -> int:
        return int(self.offsets.shape[0])

    def level(self, texture: int, level: int) -> NDArray[np.uint8]:
        """Mip level ``level`` of texture ``texture`` as uint8 (s, s, 4) RGB + luma,
        s = size >> level (row-major, untiled; for inspection and tests)."""
        if not (0 <= texture < self.n_textures and 0 <= level < self.n_levels):
            raise GeometryError(
                f"MipAtlas.level: texture {texture}, level {level} outside "
                f"{self.n_textures} textures x {self.n_levels} levels"
            )
        s = self.size >> level
        side = max(s, _TILE)
        start = int(self.offsets[level])
        flat = self.texels[texture, start : start + side * side]
        tiles = flat.reshape(side // _TILE, side // _TILE, _TILE, _TILE).transpose(0, 2, 1, 3)
        words = tiles.reshape(side, side)[:s, :s]
        shifts = np.array([0, 8, 16, 24], dtype=np.uint32)
        return ((words[..., None] >> shifts) & 255).astype(np.uint8)


@dataclass(frozen=True, eq=False)
class RenderOut:
    """One rendered frame; pixel ``[v, u]`` (row, column).

    Attributes:
        depth: float32 (H, W), camera-frame z in metres; 0 where nothing was hit.
        instance: uint16 (H, W), instance id of the visible triangle; 0 where nothing.
        material: uint16 (H, W), material id of the visible triangle; 0 where nothing.
        color: float32 (H, W, 3) RGB in [0, 1] = filtered texel colour * shade, or None
            when not requested.
        texel_gray: float32 (H, W) in [0, 1], luma of the filtered texel without shade
            (input to the thermal texture), or None when not requested.
    """

    depth: NDArray[np.float32]
    instance: NDArray[np.uint16]
    material: NDArray[np.uint16]
    color: NDArray[np.float32] | None
    texel_gray: NDArray[np.float32] | None


# --------------------------------------------------------------------------- mipmaps


def build_mipmaps(textures: ArrayLike) -> MipAtlas:
    """Build the mip pyramids of a set of square RGB textures.

    Args:
        textures: uint8 (n_tex, S, S, 3) RGB, S a power of two (>= 1).

    Returns:
        A :class:`MipAtlas` holding levels 0..log2(S) of every texture; texel (x, y)
        of level L (side S >> L) is the rounded mean of the 2^L x 2^L block of level 0
        it covers (a box-filter pyramid). Each texel also carries its luma
        ``0.299 R + 0.587 G + 0.114 B`` (of the unrounded mean), rounded.

    Raises:
        GeometryError: wrong shape or dtype, or S not a power of two.
    """
    tex = np.asarray(textures)
    if tex.ndim != 4 or tex.shape[3] != 3 or tex.shape[1] != tex.shape[2]:
        raise GeometryError(f"build_mipmaps: expected (n_tex, S, S, 3), got {tex.shape}")
    if tex.dtype != np.uint8:
        raise GeometryError(f"build_mipmaps: expected dtype uint8, got {tex.dtype}")
    n_tex, size = tex.shape[0], tex.shape[1]
    if n_tex < 1 or size < 1 or size & (size - 1):
        raise GeometryError(
            f"build_mipmaps: need >= 1 texture of power-of-two side, got {tex.shape}"
        )
    n_levels = size.bit_length()
    sides = [max(size >> level, _TILE) for level in range(n_levels)]
    offsets = np.concatenate([[0], np.cumsum([s * s for s in sides])]).astype(np.int64)
    texels = np.empty((n_tex, int(offsets[-1])), dtype=np.uint32)
    level = tex.astype(np.float64)
    for lev, side in enumerate(sides):
        if lev > 0:
            # 2x2 box filter of the unrounded previous level = mean of a 2^L block of
            # level 0, rounded once below (no drift across levels).
            level = 0.25 * (
                level[:, 0::2, 0::2]
                + level[:, 1::2, 0::2]
                + level[:, 0::2, 1::2]
                + level[:, 1::2, 1::2]
            )
        rgb = np.rint(level).astype(np.uint32)
        luma = np.rint(level @ np.asarray(_LUMA)).clip(0, 255).astype(np.uint32)
        packed = rgb[..., 0] | (rgb[..., 1] << 8) | (rgb[..., 2] << 16) | (luma << 24)
        texels[:, offsets[lev] : offsets[lev + 1]] = _to_tiles(packed, side)
    return MipAtlas(texels=texels, offsets=offsets[:-1].copy(), size=size)


def _to_tiles(level: NDArray[np.uint32], side: int) -> NDArray[np.uint32]:
    """(n, s, s) row-major texels -> (n, side * side) in 4x4 tiles (see MipAtlas).

    A level smaller than a tile (s < side) is repeated to fill it, which keeps wrap
    addressing with ``side`` exact since ``s`` divides ``side``.
    """
    n, s = level.shape[0], level.shape[1]
    if s < side:
        level = np.tile(level, (1, side // s, side // s))
    tiles = level.reshape(n, side // _TILE, _TILE, side // _TILE, _TILE).transpose(0, 1, 3, 2, 4)
    return tiles.reshape(n, side * side)


# --------------------------------------------------------------------------- numba kernel


@njit(cache=True, nogil=True, error_model="numpy")
def _clip_polygon(src, n_src, dst, pa, pb, pc, pd, z_exact):
    """Clip polygon ``src[:n_src]`` (camera frame) to ``pa x + pb y + pc z + pd >= 0``.

    Writes the result to ``dst`` and returns its corner count. The intersection on an
    edge is always interpolated from the inside corner to the outside one, so two
    triangles sharing an edge produce the bit-same point. ``z_exact > 0`` forces the
    z of new corners to that value (the near plane).
    """
    m = 0
    for k in range(n_src):
        k2 = k + 1 if k + 1 < n_src else 0
        da = pa * src[k, 0] + pb * src[k, 1] + pc * src[k, 2] + pd
        db = pa * src[k2, 0] + pb * src[k2, 1] + pc * src[k2, 2] + pd
        a_in = da >= 0.0
        if a_in:
            dst[m, 0] = src[k, 0]
            dst[m, 1] = src[k, 1]
            dst[m, 2] = src[k, 2]
            m += 1
        if a_in != (db >= 0.0):
            if a_in:
                i_k, o_k, d_in, d_out = k, k2, da, db
            else:
                i_k, o_k, d_in, d_out = k2, k, db, da
            t = d_in / (d_in - d_out)
            for c in range(3):
                dst[m, c] = src[i_k, c] + t * (src[o_k, c] - src[i_k, c])
            if z_exact > 0.0:
                dst[m, 2] = z_exact
            m += 1
    return m


@njit(cache=True, nogil=True, error_model="numpy")
def _raster_triangle(x0, y0, x1, y1, x2, y2, wa, wb, wc, tri, zbuf, idbuf):
    """Rasterize one triangle with snapped corners (int, 1/_SUB pixel) into the buffers.

    Pixel ``(i, j)`` is covered when every edge function ``E`` satisfies ``E > 0``, or
    ``E >= 0`` on a top or left edge (top-left rule), evaluated exactly in int64. It is
    written when ``w = wa i + wb j + wc`` (= 1/z) is strictly larger than ``zbuf``.
    """
    height, width = zbuf.shape
    area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
    if area == 0:
        return
    if area < 0:  # orient so that the interior has E > 0 (back faces are drawn too)
        x1, y1, x2, y2 = x2, y2, x1, y1
    sub = _SUB
    xmin = max(-((-min(x0, x1, x2)) // sub), 0)
    xmax = min(max(x0, x1, x2) // sub, width - 1)
    ymin = max(-((-min(y0, y1, y2)) // sub), 0)
    ymax = min(max(y0, y1, y2) // sub, height - 1)
    if xmin > xmax or ymin > ymax:
        return
    # Edge a->b: E(i, j) = dx (sub j - ay) - dy (sub i - ax) = A i + B j + C.
    a_0 = -(y1 - y0) * sub
    b_0 = (x1 - x0) * sub
    c_0 = (y1 - y0) * x0 - (x1 - x0) * y0
    if (y1 - y0) < 0 or ((y1 - y0) == 0 and (x1 - x0) > 0):
        c_0 += 1  # top-left edge: E >= 0 counts, i.e. E + 1 > 0
    a_1 = -(y2 - y1) * sub
    b_1 = (x2 - x1) * sub
    c_1 = (y2 - y1) * x1 - (x2 - x1) * y1
    if (y2 - y1) < 0 or ((y2 - y1) == 0 and (x2 - x1) > 0):
        c_1 += 1
    a_2 = -(y0 - y2) * sub
    b_2 = (x0 - x2) * sub
    c_2 = (y0 - y2) * x2 - (x0 - x2) * y2
    if (y0 - y2) < 0 or ((y0 - y2) == 0 and (x0 - x2) > 0):
        c_2 += 1
    # Span of i with A i + (B j + C) > 0 per edge, solved exactly and without a
    # division per row: R_j = -(B j + C) = q D + r (floor division by D = |A|) is
    # stepped row by row; the bound is i >= q + 1 (A > 0) or i <= -q - 1 (A < 0).
    q_0, r_0, dq_0, dr_0, d_0 = _edge_walk_init(a_0, b_0, c_0, ymin)
    q_1, r_1, dq_1, dr_1, d_1 = _edge_walk_init(a_1, b_1, c_1, ymin)
    q_2, r_2, dq_2, dr_2, d_2 = _edge_walk_init(a_2, b_2, c_2, ymin)
    for j in range(ymin, ymax + 1):
        lo = xmin
        hi = xmax
        if a_0 > 0:
            lo = max(lo, q_0 + 1)
        elif a_0 < 0:
            hi = min(hi, -q_0 - 1)
        elif b_0 * j + c_0 <= 0:  # horizontal edge, row outside
            hi = -1
        if a_1 > 0:
            lo = max(lo, q_1 + 1)
        elif a_1 < 0:
            hi = min(hi, -q_1 - 1)
        elif b_1 * j + c_1 <= 0:
            hi = -1
        if a_2 > 0:
            lo = max(lo, q_2 + 1)
        elif a_2 < 0:
            hi = min(hi, -q_2 - 1)
        elif b_2 * j + c_2 <= 0:
            hi = -1
        if lo <= hi:
            w_row = wb * j + wc
            zrow = zbuf[j]
            idrow = idbuf[j]
            for i in range(lo, hi + 1):  # branch-free so that LLVM vectorizes it
                w = wa * i + w_row
                nearer = w > zrow[i]
                zrow[i] = w if nearer else zrow[i]
                idrow[i] = tri if nearer else idrow[i]
        q_0 += dq_0
        r_0 += dr_0
        if r_0 >= d_0:
            q_0 += 1
            r_0 -= d_0
        q_1 += dq_1
        r_1 += dr_1
        if r_1 >= d_1:
            q_1 += 1
            r_1 -= d_1
        q_2 += dq_2
        r_2 += dr_2
        if r_2 >= d_2:
            q_2 += 1
            r_2 -= d_2


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _edge_walk_init(a, b, c, j0):
    """Start of the exact row walk of edge ``E = a i + b j + c`` (int64) at row ``j0``.

    Returns ``(q, r, dq, dr, d)``: ``-(b j0 + c) = q d + r`` and ``-b = dq d + dr`` with
    ``d = |a|`` and ``0 <= r, dr < d`` (floor division); all zero with ``d = 1`` for a
    horizontal edge (a = 0), which the caller tests directly.
    """
    d = abs(a)
    if d == 0:
        return 0, 0, 0, 0, 1
    rr = -(b * j0 + c)
    q = rr // d
    dq = (-b) // d
    return q, rr - q * d, dq, -b - dq * d, d


@njit(cache=True, nogil=True, error_model="numpy")
def _visibility(vertices, uv, R, t, fx, fy, cx, cy, width, height, near, far, cull_back):
    """Depth pass: returns ``(zbuf, idbuf, planes)``.

    ``zbuf`` float64 (H, W) holds 1/z of the nearest surface (1/far where none),
    ``idbuf`` int32 (H, W) the triangle index (-1 where none) and ``planes`` float64
    (T, 9) the pixel-linear planes ``(a, b, c)`` with ``value = a u + b v + c`` of
    ``1/z``, ``s/z`` and ``t/z`` (s, t texture coordinates) for each drawn triangle.
    """
    n_tri = vertices.shape[0]
    zbuf = np.full((height, width), 1.0 / far)
    idbuf = np.full((height, width), -1, dtype=np.int32)
    planes = np.empty((n_tri, 9))  # rows of culled triangles stay unset and unread
    P = np.empty((3, 3))
    poly_a = np.empty((16, 3))
    poly_b = np.empty((16, 3))
    sx = np.empty(16, dtype=np.int64)
    sy = np.empty(16, dtype=np.int64)
    # Frustum half-spaces through the camera centre, 1 pixel of margin: u >= -1,
    # u <= W, v >= -1, v <= H (as linear forms in camera-frame x, y, z).
    left_c = cx + 1.0
    right_c = width - cx
    top_c = cy + 1.0
    bottom_c = height - cy
    g_left = cx + _GUARD_PX
    g_right = (width - 1.0 + _GUARD_PX) - cx
    g_top = cy + _GUARD_PX
    g_bottom = (height - 1.0 + _GUARD_PX) - cy
    for tri in range(n_tri):
        for k in range(3):
            wx = vertices[tri, k, 0]
            wy = vertices[tri, k, 1]
            wz = vertices[tri, k, 2]
            for r in range(3):
                P[k, r] = R[r, 0] * wx + R[r, 1] * wy + R[r, 2] * wz + t[r]
        # --- frustum culling: all corners outside one plane.
        out_near = out_far = out_l = out_r = out_t = out_b = True
        for k in range(3):
            x = P[k, 0]
            y = P[k, 1]
            z = P[k, 2]
            out_near &= z < near
            out_far &= z > far
            out_l &= fx * x + left_c * z < 0.0
            out_r &= -fx * x + right_c * z < 0.0
            out_t &= fy * y + top_c * z < 0.0
            out_b &= -fy * y + bottom_c * z < 0.0
        if out_near or out_far or out_l or out_r or out_t or out_b:
            continue
        # --- attribute planes from the unclipped triangle. A ray z * r, with
        # r = ((u - cx)/fx, (v - cy)/fy, 1), meets the plane P0 + s e1 + t e2 at
        # 1/z = (r.n)/(P0.n), s/z = r.(e2 x P0)/(P0.n), t/z = r.(P0 x e1)/(P0.n),
        # n = e1 x e2 (Cramer's rule on [r, -e1, -e2] (z, s, t) = P0).
        e1x = P[1, 0] - P[0, 0]
        e1y = P[1, 1] - P[0, 1]
        e1z = P[1, 2] - P[0, 2]
        e2x = P[2, 0] - P[0, 0]
        e2y = P[2, 1] - P[0, 1]
        e2z = P[2, 2] - P[0, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        n_norm = math.sqrt(nx * nx + ny * ny + nz * nz)
        denom = nx * P[0, 0] + ny * P[0, 1] + nz * P[0, 2]
        if n_norm == 0.0 or abs(denom) <= 1e-9 * n_norm:
            continue  # degenerate, or its plane passes through the camera centre
        if cull_back and denom > 0.0:
            continue  # normal (corners counter-clockwise) points away from the camera
        inv = 1.0 / denom
        px0 = P[0, 0]
        py0 = P[0, 1]
        pz0 = P[0, 2]
        # s-plane: e2 x P0 ; t-plane: P0 x e1
        sxv = (e2y * pz0 - e2z * py0) * inv
        syv = (e2z * px0 - e2x * pz0) * inv
        szv = (e2x * py0 - e2y * px0) * inv
        txv = (py0 * e1z - pz0 * e1y) * inv
        tyv = (pz0 * e1x - px0 * e1z) * inv
        tzv = (px0 * e1y - py0 * e1x) * inv
        wxv = nx * inv
        wyv = ny * inv
        wzv = nz * inv
        u0 = np.float64(uv[tri, 0, 0])
        v0 = np.float64(uv[tri, 0, 1])
        du1 = np.float64(uv[tri, 1, 0]) - u0
        dv1 = np.float64(uv[tri, 1, 1]) - v0
        du2 = np.float64(uv[tri, 2, 0]) - u0
        dv2 = np.float64(uv[tri, 2, 1]) - v0
        # texture-u/z and texture-v/z in ray space, then all three in pixel space.
        ux = u0 * wxv + du1 * sxv + du2 * txv
        uy = u0 * wyv + du1 * syv + du2 * tyv
        uz = u0 * wzv + du1 * szv + du2 * tzv
        vx = v0 * wxv + dv1 * sxv + dv2 * txv
        vy = v0 * wyv + dv1 * syv + dv2 * tyv
        vz = v0 * wzv + dv1 * szv + dv2 * tzv
        planes[tri, 0] = wxv / fx
        planes[tri, 1] = wyv / fy
        planes[tri, 2] = wzv - wxv * cx / fx - wyv * cy / fy
        planes[tri, 3] = ux / fx
        planes[tri, 4] = uy / fy
        planes[tri, 5] = uz - ux * cx / fx - uy * cy / fy
        planes[tri, 6] = vx / fx
        planes[tri, 7] = vy / fy
        planes[tri, 8] = vz - vx * cx / fx - vy * cy / fy
        # --- clipping.
        for k in range(3):
            for c in range(3):
                poly_a[k, c] = P[k, c]
        n_poly = 3
        src = poly_a
        dst = poly_b
        if P[0, 2] < near or P[1, 2] < near or P[2, 2] < near:
            n_poly = _clip_polygon(src, n_poly, dst, 0.0, 0.0, 1.0, -near, near)
            src, dst = dst, src
        need_l = need_r = need_t = need_b = False
        for k in range(n_poly):
            x = src[k, 0]
            y = src[k, 1]
            z = src[k, 2]
            need_l |= fx * x + g_left * z < 0.0
            need_r |= -fx * x + g_right * z < 0.0
            need_t |= fy * y + g_top * z < 0.0
            need_b |= -fy * y + g_bottom * z < 0.0
        if need_l:
            n_poly = _clip_polygon(src, n_poly, dst, fx, 0.0, g_left, 0.0, 0.0)
            src, dst = dst, src
        if need_r:
            n_poly = _clip_polygon(src, n_poly, dst, -fx, 0.0, g_right, 0.0, 0.0)
            src, dst = dst, src
        if need_t:
            n_poly = _clip_polygon(src, n_poly, dst, 0.0, fy, g_top, 0.0, 0.0)
            src, dst = dst, src
        if need_b:
            n_poly = _clip_polygon(src, n_poly, dst, 0.0, -fy, g_bottom, 0.0, 0.0)
            src, dst = dst, src
        if n_poly < 3:
            continue
        # --- project and snap, then rasterize the fan (0, k, k + 1).
        for k in range(n_poly):
            iz = 1.0 / src[k, 2]
            sx[k] = np.int64(math.floor((fx * src[k, 0] * iz + cx) * _SUB + 0.5))
            sy[k] = np.int64(math.floor((fy * src[k, 1] * iz + cy) * _SUB + 0.5))
        for k in range(1, n_poly - 1):
            _raster_triangle(
                sx[0],
                sy[0],
                sx[k],
                sy[k],
                sx[k + 1],
                sy[k + 1],
                planes[tri, 0],
                planes[tri, 1],
                planes[tri, 2],
                tri,
                zbuf,
                idbuf,
            )
    return zbuf, idbuf, planes


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bilinear(texels, tex, offset, side, scale, s, t, want_rgb):
    """Bilinear sample of one level (side ``side``, wrap) at level-0 texel coords (s, t).

    Returns ``(r, g, b, luma)`` in 0..255 (r, g, b are 0 when ``want_rgb`` is False).
    """
    x = s * scale - 0.5
    y = t * scale - 0.5
    xf = math.floor(x)
    yf = math.floor(y)
    ax = x - xf
    ay = y - yf
    mask = side - 1
    ix0 = np.int64(xf) & mask
    iy0 = np.int64(yf) & mask
    ix1 = (ix0 + 1) & mask
    iy1 = (iy0 + 1) & mask
    # 4x4 tiled layout (MipAtlas): tile row stride 4 * side, tile stride 16.
    row0 = offset + (iy0 >> 2) * (side << 2) + ((iy0 & 3) << 2)
    row1 = offset + (iy1 >> 2) * (side << 2) + ((iy1 & 3) << 2)
    ix0 = ((ix0 >> 2) << 4) + (ix0 & 3)
    ix1 = ((ix1 >> 2) << 4) + (ix1 & 3)
    t00 = np.int64(texels[tex, row0 + ix0])
    t01 = np.int64(texels[tex, row0 + ix1])
    t10 = np.int64(texels[tex, row1 + ix0])
    t11 = np.int64(texels[tex, row1 + ix1])
    w00 = (1.0 - ax) * (1.0 - ay)
    w01 = ax * (1.0 - ay)
    w10 = (1.0 - ax) * ay
    w11 = ax * ay
    luma = w00 * (t00 >> 24) + w01 * (t01 >> 24) + w10 * (t10 >> 24) + w11 * (t11 >> 24)
    r = g = b = 0.0
    if want_rgb:
        r = w00 * (t00 & 255) + w01 * (t01 & 255) + w10 * (t10 & 255) + w11 * (t11 & 255)
        g = (
            w00 * ((t00 >> 8) & 255)
            + w01 * ((t01 >> 8) & 255)
            + w10 * ((t10 >> 8) & 255)
            + w11 * ((t11 >> 8) & 255)
        )
        b = (
            w00 * ((t00 >> 16) & 255)
            + w01 * ((t01 >> 16) & 255)
            + w10 * ((t10 >> 16) & 255)
            + w11 * ((t11 >> 16) & 255)
        )
    return r, g, b, luma


@njit(cache=True, nogil=True, error_model="numpy")
def _resolve(
    idbuf,
    planes,
    texture,
    instance,
    material,
    shade,
    texels,
    offsets,
    tex_size,
    want_color,
    want_gray,
    trilinear,
):
    """Shading pass: one texture lookup per covered pixel. Returns the output images.

    Mip level: ``lod = log2(rho)`` with ``rho`` the longer of the texel footprints of a
    pixel step along u and along v (the usual isotropic choice); ``log2`` is evaluated
    piecewise-linearly between octaves (``lod = L + rho / 2^L - 1`` for
    ``2^L <= rho < 2^(L+1)``), continuous and monotone, and far cheaper than libm.
    """
    height, width = idbuf.shape
    max_level = offsets.shape[0] - 1
    depth = np.zeros((height, width), dtype=np.float32)
    inst = np.zeros((height, width), dtype=np.uint16)
    mat = np.zeros((height, width), dtype=np.uint16)
    color = np.zeros((height if want_color else 0, width, 3), dtype=np.float32)
    gray = np.zeros((height if want_gray else 0, width), dtype=np.float32)
    want_tex = want_color or want_gray
    inv255 = 1.0 / 255.0
    max_rho = float(1 << max_level)
    for j in range(height):
        cur = -1
        # per-triangle constants, reloaded when the triangle changes along the row
        wa = wr = sa = sb = sr = ta = tb = tr = wb = k_shade = 0.0
        tex = 0
        tri_inst = tri_mat = np.uint16(0)
        for i in range(width):
            tri = idbuf[j, i]
            if tri < 0:
                continue
            if tri != cur:
                cur = tri
                wa = planes[tri, 0]
                wb = planes[tri, 1]
                wr = wb * j + planes[tri, 2]
                sa = planes[tri, 3]
                sb = planes[tri, 4]
                sr = sb * j + planes[tri, 5]
                ta = planes[tri, 6]
                tb = planes[tri, 7]
                tr = tb * j + planes[tri, 8]
                tex = texture[tri]
                k_shade = shade[tri] * inv255
                tri_inst = instance[tri]
                tri_mat = material[tri]
            z = 1.0 / (wa * i + wr)
            depth[j, i] = z
            inst[j, i] = tri_inst
            mat[j, i] = tri_mat
            if not want_tex:
                continue
            s = (sa * i + sr) * z
            tt = (ta * i + tr) * z
            # Texel footprint of one pixel step: d/du of s = (s/z) / (1/z), etc.
            dsdu = (sa - s * wa) * z
            dtdu = (ta - tt * wa) * z
            dsdv = (sb - s * wb) * z
            dtdv = (tb - tt * wb) * z
            rho = math.sqrt(max(dsdu * dsdu + dtdu * dtdu, dsdv * dsdv + dtdv * dtdv))
            if rho >= max_rho:
                level = max_level
                frac = 0.0
            else:
                level = 0
                octave = 1.0
                while rho >= 2.0 * octave:
                    octave *= 2.0
                    level += 1
                frac = rho / octave - 1.0 if rho > 1.0 else 0.0
                if not trilinear:
                    if frac >= 0.5:
                        level += 1
                    frac = 0.0
            side = max(tex_size >> level, 4)
            scale = 1.0 / (1 << level)
            r, g, b, y = _bilinear(texels, tex, offsets[level], side, scale, s, tt, want_color)
            if frac > 0.0:
                r2, g2, b2, y2 = _bilinear(
                    texels,
                    tex,
                    offsets[level + 1],
                    max(side >> 1, 4),
                    0.5 * scale,
                    s,
                    tt,
                    want_color,
                )
                r += frac * (r2 - r)
                g += frac * (g2 - g)
                b += frac * (b2 - b)
                y += frac * (y2 - y)
            if want_color:
                color[j, i, 0] = r * k_shade
                color[j, i, 1] = g * k_shade
                color[j, i, 2] = b * k_shade
            if want_gray:
                gray[j, i] = y * inv255
    return depth, inst, mat, color, gray


# --------------------------------------------------------------------------- public API


def render(
    mesh: Mesh,
    textures_mips: MipAtlas,
    K: tuple[float, float, float, float],
    width: int,
    height: int,
    T_camera_world: ArrayLike,
    near: float = 0.1,
    far: float = 20.0,
    *,
    sample_color: bool = True,
    sample_gray: bool = True,
    filtering: Literal["trilinear", "bilinear"] = "trilinear",
    cull_backfaces: bool = False,
) -> RenderOut:
    """Render ``mesh`` from a pinhole camera with a z-buffer.

    Args:
        mesh: the world's triangles, world frame (metres).
        textures_mips: textures from :func:`build_mipmaps`; ``mesh.texture`` indexes it.
        K: intrinsics ``(fx, fy, cx, cy)`` in pixels (pixel centre (0, 0) top-left).
        width, height: image size in pixels.
        T_camera_world: float64 (4, 4), maps world points into the camera frame
            (x right, y down, z forward).
        near, far: clip distances along the camera z axis in metres; surfaces at
            ``z >= far`` are not drawn.
        sample_color: produce ``color`` (RGB texel * shade). False skips RGB sampling.
        sample_gray: produce ``texel_gray`` (texel luma without shade). A thermal pass
            sets ``sample_color=False`` and gets depth, material and luma only; with
            both False no texture is read at all.
        filtering: ``"trilinear"`` (blend the two nearest mip levels; no seams where
            the level changes, least shimmer) or ``"bilinear"`` (nearest level, faster).
        cull_backfaces: drop triangles whose corners appear clockwise in the image, i.e.
            whose right-handed normal ``(p1 - p0) x (p2 - p0)`` points away from the
            camera. Off by default: walls are seen from both sides.

    Returns:
        :class:`RenderOut` with (height, width) images; the same inputs always give
        byte-identical outputs.

    Raises:
        GeometryError: bad intrinsics, image size, clip distances, transform, or a
            texture index outside the atlas.
    """
    fx, fy, cx, cy = (float(k) for k in K)
    if not all(math.isfinite(k) for k in (fx, fy, cx, cy)) or fx <= 0.0 or fy <= 0.0:
        raise GeometryError(f"render: K must be finite with fx, fy > 0, got {K}")
    if int(width) != width or int(height) != height or width <= 0 or height <= 0:
        raise GeometryError(f"render: image size must be positive ints, got {width}x{height}")
    if not (math.isfinite(near) and math.isfinite(far) and 0.0 < near < far):
        raise GeometryError(f"render: need 0 < near < far (finite), got {near}, {far}")
    if filtering not in ("trilinear", "bilinear"):
        raise GeometryError(f"render: filtering must be 'trilinear' or 'bilinear', got {filtering}")
    T = check_transform(T_camera_world, "T_camera_world")
    if mesh.n_triangles and int(np.max(mesh.texture)) >= textures_mips.n_textures:
        raise GeometryError(
            f"render: texture index {int(np.max(mesh.texture))} outside the atlas of "
            f"{textures_mips.n_textures} textures"
        )
    R = np.ascontiguousarray(T[:3, :3])
    t = np.ascontiguousarray(T[:3, 3])
    _, idbuf, planes = _visibility(
        mesh.vertices,
        mesh.uv,
        R,
        t,
        fx,
        fy,
        cx,
        cy,
        int(width),
        int(height),
        float(near),
        float(far),
        bool(cull_backfaces),
    )
    depth, inst, mat, color, gray = _resolve(
        idbuf,
        planes,
        mesh.texture,
        mesh.instance,
        mesh.material,
        mesh.shade,
        textures_mips.texels,
        textures_mips.offsets,
        textures_mips.size,
        bool(sample_color),
        bool(sample_gray),
        filtering == "trilinear",
    )
    return RenderOut(
        depth=depth,
        instance=inst,
        material=mat,
        color=color if sample_color else None,
        texel_gray=gray if sample_gray else None,
    )
