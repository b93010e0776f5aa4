"""Speed of the software rasterizer (``wardmap.sim.raster``) on one core.

Builds a synthetic hospital corridor (tiled floor, walls and ceiling plus random
furniture boxes, noise textures), flies a camera along it and prints a markdown table of
milliseconds per frame (median over the timed frames, after JIT warm-up) for the RGB pass
(640x480, colour + luma) and the thermal pass (388x284, depth + material + luma).

Usage: ``python bench/raster_speed.py [--frames 50] [--boxes 200] [--seed 0]``
"""

from __future__ import annotations

import os

# One core: set before numba is imported (the kernels are serial anyway).
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import argparse
import functools
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wardmap.sim.raster import Mesh, MipAtlas, RenderOut, build_mipmaps, render

CORRIDOR_LENGTH_M = 80.0
CORRIDOR_WIDTH_M = 3.0
CORRIDOR_HEIGHT_M = 2.8
TILE_M = 0.5
TEXELS_PER_M = 256.0
TEX_SIZE = 256
N_TEXTURES = 8
RGB_K = (320.0, 320.0, 319.5, 239.5)  # 90 deg horizontal field of view at 640x480
THERMAL_K = (220.0, 220.0, 193.5, 141.5)


def _quad(
    p0: NDArray[np.float64], du: NDArray[np.float64], dv: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Two triangles (2, 3, 3) of the parallelogram p0 + a du + b dv and their uv (2, 3, 2)."""
    c = np.array([p0, p0 + du, p0 + du + dv, p0 + dv])
    lu, lv = np.linalg.norm(du) * TEXELS_PER_M, np.linalg.norm(dv) * TEXELS_PER_M
    t = np.array([[0.0, 0.0], [lu, 0.0], [lu, lv], [0.0, lv]])
    idx = np.array([[0, 1, 2], [0, 2, 3]])
    return c[idx], t[idx]


def _tiled_plane(
    origin: NDArray[np.float64], du: NDArray[np.float64], dv: NDArray[np.float64], nu: int, nv: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    tris, uvs = [], []
    for a in range(nu):
        for b in range(nv):
            q, t = _quad(origin + a * du + b * dv, du, dv)
            tris.append(q)
            uvs.append(
                t + np.array([a * np.linalg.norm(du), b * np.linalg.norm(dv)]) * TEXELS_PER_M
            )
    return np.concatenate(tris), np.concatenate(uvs)


def _box(
    center: NDArray[np.float64], size: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """12 triangles of an axis-aligned box."""
    lo = center - size / 2
    ex, ey, ez = np.diag(size)
    faces = [
        (lo, ex, ey),
        (lo + ez, ex, ey),  # bottom, top
        (lo, ex, ez),
        (lo + ey, ex, ez),  # front, back
        (lo, ey, ez),
        (lo + ex, ey, ez),  # sides
    ]
    tris, uvs = zip(*(_quad(p, u, v) for p, u, v in faces), strict=True)
    return np.concatenate(tris), np.concatenate(uvs)


def build_corridor(n_boxes: int, seed: int) -> tuple[Mesh, NDArray[np.uint8]]:
    """A corridor along +x (floor z = 0) with ``n_boxes`` boxes; returns (mesh, textures)."""
    rng = np.random.default_rng(seed)
    L, W, H = CORRIDOR_LENGTH_M, CORRIDOR_WIDTH_M, CORRIDOR_HEIGHT_M
    nl, nw, nh = int(L / TILE_M), int(W / TILE_M), int(np.ceil(H / TILE_M))
    ex, ey = np.eye(3)[:2] * TILE_M
    hz = np.array([0.0, 0.0, H / nh])
    parts = [
        (_tiled_plane(np.zeros(3), ex, ey, nl, nw), 0, 0, 1, 0.9),  # floor
        (_tiled_plane(np.array([0.0, 0.0, H]), ex, ey, nl, nw), 1, 0, 2, 0.6),  # ceiling
        (_tiled_plane(np.zeros(3), ex, hz, nl, nh), 2, 0, 3, 0.8),  # wall y = 0
        (_tiled_plane(np.array([0.0, W, 0.0]), ex, hz, nl, nh), 2, 0, 3, 0.7),  # wall y = W
    ]
    for b in range(n_boxes):
        size = rng.uniform([0.3, 0.3, 0.4], [1.2, 0.8, 1.8])
        c = np.array([rng.uniform(0.5, L - 0.5), rng.choice([size[1] / 2, W - size[1] / 2]), 0.0])
        c[2] = size[2] / 2
        parts.append((_box(c, size), int(rng.integers(3, N_TEXTURES)), b + 1, 10, 0.75))
    verts, uvs, tex, inst, mat, shade = [], [], [], [], [], []
    for (v, t), ti, ii, mi, si in parts:
        n = v.shape[0]
        verts.append(v)
        uvs.append(t)
        tex.append(np.full(n, ti))
        inst.append(np.full(n, ii))
        mat.append(np.full(n, mi))
        shade.append(np.full(n, si))
    mesh = Mesh(
        vertices=np.concatenate(verts),
        uv=np.concatenate(uvs),
        texture=np.concatenate(tex),
        instance=np.concatenate(inst),
        material=np.concatenate(mat),
        shade=np.concatenate(shade),
    )
    textures = rng.integers(0, 256, size=(N_TEXTURES, TEX_SIZE, TEX_SIZE, 3), dtype=np.uint8)
    return mesh, textures


def camera_path(n: int) -> list[NDArray[np.float64]]:
    """``T_camera_world`` poses walking down the corridor at 1.2 m, yaw swinging +-60 deg."""
    poses = []
    for k in range(n):
        x = 2.0 + (CORRIDOR_LENGTH_M - 4.0) * k / max(n - 1, 1)
        yaw = np.radians(60.0) * np.sin(k * 0.7)
        # camera axes in world: z forward, x right, y down
        fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        R_world_camera = np.column_stack([right, down, fwd])
        T_world_camera = np.eye(4)
        T_world_camera[:3, :3] = R_world_camera
        T_world_camera[:3, 3] = (x, CORRIDOR_WIDTH_M / 2, 1.2)
        poses.append(np.asarray(np.linalg.inv(T_world_camera), dtype=np.float64))
    return poses


def _render_frame(
    mesh: Mesh,
    mips: MipAtlas,
    K: tuple[float, float, float, float],
    width: int,
    height: int,
    options: dict[str, Any],
    T_camera_world: NDArray[np.float64],
) -> RenderOut:
    return render(mesh, mips, K, width, height, T_camera_world, **options)


def _time_pass(
    fn: Callable[[NDArray[np.float64]], object], poses: list[NDArray[np.float64]], warmup: int
) -> float:
    """Median wall time in ms of ``fn(T)`` over ``poses`` after ``warmup`` calls."""
    for T in poses[:warmup]:
        fn(T)
    times = []
    for T in poses:
        t0 = time.perf_counter()
        fn(T)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--boxes", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--warmup", type=int, default=3)
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    t0 = time.perf_counter()
    mesh, textures = build_corridor(args.boxes, args.seed)
    mips = build_mipmaps(textures)
    poses = camera_path(args.frames)
    setup_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    render(mesh, mips, RGB_K, 640, 480, poses[0])
    first_call_s = time.perf_counter() - t0

    rows: list[tuple[str, tuple[float, float, float, float], int, int, dict[str, Any]]] = [
        (
            "RGB 640x480, trilinear (color + gray)",
            RGB_K,
            640,
            480,
            {"sample_color": True, "sample_gray": True},
        ),
        (
            "RGB 640x480, bilinear (color + gray)",
            RGB_K,
            640,
            480,
            {"sample_color": True, "sample_gray": True, "filtering": "bilinear"},
        ),
        (
            "RGB 640x480, depth/labels only",
            RGB_K,
            640,
            480,
            {"sample_color": False, "sample_gray": False},
        ),
        (
            "thermal 388x284, trilinear (depth, material, gray)",
            THERMAL_K,
            388,
            284,
            {"sample_color": False, "sample_gray": True},
        ),
    ]
    print(
        f"scene: {mesh.n_triangles} triangles, {args.boxes} boxes, "
        f"{mips.n_textures} textures {mips.size}^2; setup {setup_s:.2f} s, "
        f"first render (JIT compile or cache load) {first_call_s:.2f} s"
    )
    print(f"median over {args.frames} frames after {args.warmup} warm-up frames, one core\n")
    print("| pass | ms/frame |")
    print("| --- | ---: |")
    for name, K, w, h, kw in rows:
        fn = functools.partial(_render_frame, mesh, mips, K, w, h, kw)
        print(f"| {name} | {_time_pass(fn, poses, args.warmup):.2f} |")


if __name__ == "__main__":
    main()
