"""The software rasterizer: coverage, depth, clipping, fill rule, texturing, determinism.

Scenes are synthetic with analytic ground truth: planes and quads whose projection or
ray intersection is known in closed form.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from wardmap.shared.errors import GeometryError
from wardmap.sim.raster import Mesh, MipAtlas, RenderOut, build_mipmaps, render

F64 = NDArray[np.float64]

W, H = 128, 96
K = (100.0, 100.0, 63.5, 47.5)  # 65 x 51 degree field of view


# --------------------------------------------------------------------------- helpers


def _quad_tris(corners: F64, uv: F64 | None = None) -> tuple[F64, F64]:
    """Two triangles (0, 1, 2), (0, 2, 3) of a quad given by 4 corners (4, 3)."""
    c = np.asarray(corners, dtype=np.float64)
    t = np.zeros((4, 2)) if uv is None else np.asarray(uv, dtype=np.float64)
    idx = np.array([[0, 1, 2], [0, 2, 3]])
    return c[idx], t[idx]


def _mesh(parts: list[tuple[F64, F64, int]], texture: int = 0, shade: float = 1.0) -> Mesh:
    """Mesh from (triangles (n, 3, 3), uv (n, 3, 2), instance id) parts; material = id."""
    tris = np.concatenate([p[0] for p in parts])
    uvs = np.concatenate([p[1] for p in parts])
    ids = np.concatenate([np.full(p[0].shape[0], p[2]) for p in parts])
    n = tris.shape[0]
    return Mesh(
        vertices=tris,
        uv=uvs,
        texture=np.full(n, texture),
        instance=ids,
        material=ids + 100,
        shade=np.full(n, shade),
    )


def _flat_atlas(rgb: tuple[int, int, int] = (200, 100, 50), size: int = 16) -> MipAtlas:
    tex = np.empty((1, size, size, 3), dtype=np.uint8)
    tex[:] = rgb
    return build_mipmaps(tex)


def _pose(position: F64, yaw: float, pitch: float) -> F64:
    """``T_camera_world`` of a camera at ``position`` (world, z up) looking along yaw
    (about world z, 0 = +x) and pitch (positive = down), without roll."""
    cy_, sy_ = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    fwd = np.array([cy_ * cp, sy_ * cp, -sp])
    right = np.array([sy_, -cy_, 0.0])
    down = np.cross(fwd, right)
    T_world_camera = np.eye(4)
    T_world_camera[:3, :3] = np.column_stack([right, down, fwd])
    T_world_camera[:3, 3] = position
    return np.asarray(np.linalg.inv(T_world_camera), dtype=np.float64)


def _rays_world(T_camera_world: F64, width: int = W, height: int = H) -> tuple[F64, F64]:
    """Camera centre (3,) and per-pixel world ray directions (H, W, 3) with z_cam = 1."""
    fx, fy, cx, cy = K
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)
    T_world_camera = np.asarray(np.linalg.inv(T_camera_world), dtype=np.float64)
    return T_world_camera[:3, 3], np.asarray(rays_cam @ T_world_camera[:3, :3].T, dtype=np.float64)


def _render(mesh: Mesh, atlas: MipAtlas, T_camera_world: F64 | None = None, **kw: Any) -> RenderOut:
    T = np.eye(4) if T_camera_world is None else T_camera_world
    return render(mesh, atlas, K, W, H, T, **kw)


def _floor(half_extent_m: float, instance: int = 7) -> tuple[F64, F64, int]:
    h = half_extent_m
    corners = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    tris, uv = _quad_tris(corners, corners[:, :2] * 64.0)
    return tris, uv, instance


# --------------------------------------------------------------------------- tests


def test_fronto_parallel_quad_depth_coverage_and_flat_colour() -> None:
    """A quad at z = 2 m facing the camera (camera frame = world frame): depth is
    exactly 2 inside, instance is set exactly on the pixel centres inside the projected
    rectangle (area within one row/column of analytic) and 0 elsewhere, and a flat
    texture gives texel colour * shade and its luma everywhere."""
    z = 2.0
    x0, x1, y0, y1 = -0.5, 0.3, -0.2, 0.4
    corners = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    tris, uv = _quad_tris(corners, np.array([[0, 0], [5, 0], [5, 5], [0, 5]]))
    out = _render(_mesh([(tris, uv, 3)], shade=0.5), _flat_atlas((200, 100, 50)))

    fx, fy, cx, cy = K
    u0, u1 = fx * x0 / z + cx, fx * x1 / z + cx
    v0, v1 = fy * y0 / z + cy, fy * y1 / z + cy
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    expected = (u >= u0) & (u < u1) & (v >= v0) & (v < v1)
    mask = out.instance == 3
    analytic_area = (u1 - u0) * (v1 - v0)
    assert abs(int(mask.sum()) - analytic_area) <= (u1 - u0) + (v1 - v0) + 1
    np.testing.assert_array_equal(mask, expected)
    np.testing.assert_array_equal(out.depth[mask], np.float32(z))
    assert np.all(out.depth[~mask] == 0) and np.all(out.instance[~mask] == 0)
    assert np.all(out.material[mask] == 103) and np.all(out.material[~mask] == 0)
    assert out.color is not None and out.texel_gray is not None
    expected_rgb = np.broadcast_to(np.array([200, 100, 50]) / 255 * 0.5, (int(mask.sum()), 3))
    np.testing.assert_allclose(out.color[mask], expected_rgb, atol=1e-6)
    luma = round(0.299 * 200 + 0.587 * 100 + 0.114 * 50) / 255
    np.testing.assert_allclose(out.texel_gray[mask], luma, atol=1e-6)
    assert np.all(out.color[~mask] == 0) and np.all(out.texel_gray[~mask] == 0)


@pytest.mark.parametrize("near_first", [True, False])
def test_nearer_quad_hides_farther_one_whatever_the_order(near_first: bool) -> None:
    """A small quad at 1.5 m in front of a large one at 3 m: where both project, the
    near one wins (instance and depth), independent of triangle order."""
    near_q = _quad_tris(
        np.array([[-0.2, -0.2, 1.5], [0.2, -0.2, 1.5], [0.2, 0.2, 1.5], [-0.2, 0.2, 1.5]])
    )
    far_q = _quad_tris(
        np.array([[-1.0, -1.0, 3.0], [1.0, -1.0, 3.0], [1.0, 1.0, 3.0], [-1.0, 1.0, 3.0]])
    )
    parts = [(*near_q, 1), (*far_q, 2)]
    out = _render(_mesh(parts if near_first else parts[::-1]), _flat_atlas())
    fx, _, cx, cy = K
    half = fx * 0.2 / 1.5
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    inside_near = (np.abs(u - cx) < half - 1) & (np.abs(v - cy) < half - 1)
    assert np.all(out.instance[inside_near] == 1)
    np.testing.assert_allclose(out.depth[inside_near], 1.5, rtol=1e-6)
    outside_near = (np.abs(u - cx) > half + 1) | (np.abs(v - cy) > half + 1)
    inside_far = (np.abs(u - cx) < fx / 3.0 - 1) & (np.abs(v - cy) < fx / 3.0 - 1)
    ring = outside_near & inside_far
    assert ring.sum() > 1000
    assert np.all(out.instance[ring] == 2)
    np.testing.assert_allclose(out.depth[ring], 3.0, rtol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_floor_crossing_near_plane_has_no_holes_and_analytic_depth(seed: int) -> None:
    """A 2 km floor (z = 0) under a camera 1.2 m up with random yaw and downward pitch:
    the floor triangles reach behind the camera (near clipping) and project millions of
    pixels off screen (guard-band clipping). Every pixel whose ray meets the floor
    closer than ``far`` is covered, and its depth equals the ray-plane intersection."""
    rng = np.random.default_rng(seed)
    T = _pose(
        np.array([*rng.uniform(-3, 3, 2), 1.2]), rng.uniform(-np.pi, np.pi), rng.uniform(0.1, 0.6)
    )
    far = 20.0
    out = _render(_mesh([_floor(1000.0)]), _flat_atlas(), T, far=far)
    centre, d = _rays_world(T)
    with np.errstate(divide="ignore"):
        z_true = np.where(d[..., 2] < 0, -centre[2] / d[..., 2], np.inf)
    hit = z_true < far * (1 - 1e-3)
    miss = z_true > far * (1 + 1e-3)
    assert hit.sum() > 0.2 * W * H
    assert np.all(out.instance[hit] == 7), "holes in the floor"
    np.testing.assert_allclose(out.depth[hit], z_true[hit], rtol=1e-4)
    assert np.all(out.depth[miss] == 0) and np.all(out.instance[miss] == 0)


def test_near_plane_cuts_a_wall_at_z_near() -> None:
    """A wall running obliquely past the camera from behind it to far ahead: pixels
    whose ray meets it beyond ``near`` show it at the analytic depth, pixels where the
    hit is nearer than ``near`` show nothing."""
    near = 0.5
    # wall plane x = 0.3 (camera frame) crossing the whole view, extending to z = -5.
    corners = np.array([[0.3, -50, -5.0], [0.3, 50, -5.0], [0.3, 50, 30.0], [0.3, -50, 30.0]])
    out = _render(_mesh([(*_quad_tris(corners), 4)]), _flat_atlas(), near=near)
    fx, _, cx, _ = K
    u = np.arange(W, dtype=np.float64)
    with np.errstate(divide="ignore"):
        z_col = np.where(u > cx, 0.3 * fx / (u - cx), np.inf)
    z_true = np.broadcast_to(z_col, (H, W))
    hit = (z_true > near * 1.01) & (z_true < 20.0 * 0.99)
    cut = z_true < near * 0.99
    assert hit.any() and cut.any()
    assert np.all(out.instance[hit] == 4)
    np.testing.assert_allclose(out.depth[hit], z_true[hit], rtol=1e-4)
    assert np.all(out.instance[cut] == 0)


def test_quad_split_on_its_diagonal_covers_each_pixel_once() -> None:
    """A quad whose corners and diagonal pass exactly through pixel centres (all ties
    for the fill rule), split in two triangles, in front of a background plane: no
    background pixel leaks through, and rendered alone the two triangles cover disjoint
    pixel sets whose union is the quad's coverage."""
    fx, fy, cx, cy = K
    z = 1.0
    pix = np.array([[20.0, 10.0], [90.0, 10.0], [90.0, 80.0], [20.0, 80.0]])
    corners = np.column_stack([(pix[:, 0] - cx) / fx * z, (pix[:, 1] - cy) / fy * z, np.full(4, z)])
    tris, uv = _quad_tris(corners)
    background = _quad_tris(np.array([[-5, -5, 4.0], [5, -5, 4.0], [5, 5, 4.0], [-5, 5, 4.0]]))
    atlas = _flat_atlas()
    out = _render(_mesh([(tris, uv, 1), (*background, 9)]), atlas)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    inside = (u >= 20) & (u < 90) & (v >= 10) & (v < 80)  # top-left rule on the border
    np.testing.assert_array_equal(out.instance == 1, inside)
    assert np.all(out.instance[~inside] == 9)
    cover = [
        _render(_mesh([(tris[k : k + 1], uv[k : k + 1], 1)]), atlas).instance == 1 for k in range(2)
    ]
    assert not np.any(cover[0] & cover[1]), "pixels on the diagonal written twice"
    np.testing.assert_array_equal(cover[0] | cover[1], inside)
    diag = (u - 20 == v - 10) & inside
    assert diag.sum() == 70 and np.all((cover[0] | cover[1])[diag])


@pytest.mark.parametrize("seed", [3, 4])
def test_random_triangle_fan_covers_each_pixel_at_most_once_without_cracks(seed: int) -> None:
    """A convex polygon (random angles, random tilt in depth) triangulated as a fan of
    12 triangles, plus random 3D rotation: rendering each triangle alone, no pixel is
    covered twice, and the union equals the full mesh's coverage with no crack (every
    pixel centre well inside the polygon is covered)."""
    rng = np.random.default_rng(seed)
    n = 12
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    ring = np.column_stack([0.8 * np.cos(ang), 0.6 * np.sin(ang), np.zeros(n)])
    centre = np.array([0.05, -0.03, 0.0])
    a, b = rng.uniform(-0.5, 0.5, 2)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    pts = (np.vstack([centre, ring]) @ (Ry @ Rx).T) + np.array([0.0, 0.0, 2.0])
    tris = np.stack([np.stack([pts[0], pts[1 + k], pts[1 + (k + 1) % n]]) for k in range(n)])
    uv = np.zeros((n, 3, 2))
    atlas = _flat_atlas()
    count = np.zeros((H, W), dtype=int)
    for k in range(n):
        count += _render(_mesh([(tris[k : k + 1], uv[k : k + 1], 1)]), atlas).instance == 1
    assert count.max() == 1, "a pixel covered by two triangles"
    full = _render(_mesh([(tris, uv, 1)]), atlas).instance == 1
    np.testing.assert_array_equal(full, count == 1)
    # Pixels more than one pixel inside the projected polygon must all be covered.
    fx, fy, cx, cy = K
    proj = np.column_stack([fx * pts[1:, 0] / pts[1:, 2] + cx, fy * pts[1:, 1] / pts[1:, 2] + cy])
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    inside = np.ones((H, W), dtype=bool)
    e01, e02 = proj[1] - proj[0], proj[2] - proj[0]
    orient = np.sign(e01[0] * e02[1] - e01[1] * e02[0])
    for k in range(n):
        p, q = proj[k], proj[(k + 1) % n]
        e = q - p
        dist = orient * (e[0] * (v - p[1]) - e[1] * (u - p[0])) / np.hypot(*e)
        inside &= dist > 1.0
    assert inside.sum() > 500
    assert np.all(full[inside]), "crack inside the fan"


def test_same_input_gives_byte_identical_output() -> None:
    """Two renders of the same random scene of boxes and planes (and of a copy of the
    mesh) are byte-identical in every output."""
    rng = np.random.default_rng(5)
    parts = [_floor(30.0)]
    for k in range(40):
        c = rng.uniform([-5, -5, 0.2], [5, 5, 1.0])
        s = rng.uniform(0.2, 0.8, 3)
        for ax in range(3):
            for sign in (-1, 1):
                o = c.copy()
                o[ax] += sign * s[ax] / 2
                e1, e2 = (
                    np.eye(3)[(ax + 1) % 3] * s[(ax + 1) % 3],
                    np.eye(3)[(ax + 2) % 3] * s[(ax + 2) % 3],
                )
                corners = np.array(
                    [
                        o - e1 / 2 - e2 / 2,
                        o + e1 / 2 - e2 / 2,
                        o + e1 / 2 + e2 / 2,
                        o - e1 / 2 + e2 / 2,
                    ]
                )
                parts.append((*_quad_tris(corners, rng.uniform(0, 300, (4, 2))), k + 1))
    mesh = _mesh(parts)
    tex = rng.integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    atlas = build_mipmaps(tex)
    T = _pose(np.array([-6.0, 0.3, 1.1]), 0.1, 0.15)
    a = _render(mesh, atlas, T)
    copy = Mesh(
        mesh.vertices.copy(),
        mesh.uv.copy(),
        mesh.texture.copy(),
        mesh.instance.copy(),
        mesh.material.copy(),
        mesh.shade.copy(),
    )
    b = _render(copy, atlas, T)
    assert a.color is not None and b.color is not None
    assert a.texel_gray is not None and b.texel_gray is not None
    assert (a.instance > 0).sum() > 1000
    for x, y in [
        (a.depth, b.depth),
        (a.instance, b.instance),
        (a.material, b.material),
        (a.color, b.color),
        (a.texel_gray, b.texel_gray),
    ]:
        assert x.tobytes() == y.tobytes()


@pytest.mark.parametrize("seed", [6, 7, 8])
def test_moved_camera_sees_wall_where_geometry_says(seed: int) -> None:
    """A wall x = 5 m (world) seen from random poses: every pixel whose ray meets the
    wall (within its extent and ``far``) is covered, and its depth back-projects onto
    the wall plane (ray-plane intersection within 1e-4 relative)."""
    rng = np.random.default_rng(seed)
    wall = np.array([[5.0, -10, -2], [5.0, 10, -2], [5.0, 10, 6], [5.0, -10, 6]])
    mesh = _mesh([(*_quad_tris(wall), 2)])
    T = _pose(
        np.array([*rng.uniform(-2, 2, 2), rng.uniform(0.5, 2.0)]),
        rng.uniform(-0.6, 0.6),
        rng.uniform(-0.3, 0.3),
    )
    out = _render(mesh, _flat_atlas(), T)
    centre, d = _rays_world(T)
    with np.errstate(divide="ignore", invalid="ignore"):
        z_true = np.where(d[..., 0] > 0, (5.0 - centre[0]) / d[..., 0], np.inf)
    p = centre + z_true[..., None] * d
    hit = (z_true < 19.9) & (np.abs(p[..., 1]) < 9.9) & (p[..., 2] > -1.9) & (p[..., 2] < 5.9)
    assert hit.sum() > 0.3 * W * H
    assert np.all(out.instance[hit] == 2)
    np.testing.assert_allclose(out.depth[hit], z_true[hit], rtol=1e-4)
    covered = out.depth > 0
    p_hat = centre + out.depth[..., None].astype(np.float64) * d
    np.testing.assert_allclose(p_hat[covered][:, 0], 5.0, rtol=1e-4)


def test_texture_coordinates_are_perspective_correct() -> None:
    """A floor strip textured with a horizontal ramp (texel x has red = x) seen at a
    grazing angle: the sampled red equals the analytic texture coordinate of the
    ray-floor hit minus half a texel (bilinear on a ramp, any mip level), within
    rounding; affine interpolation would be off by tens of texels."""
    ramp = np.zeros((1, 256, 256, 3), dtype=np.uint8)
    ramp[0, :, :, 0] = np.arange(256, dtype=np.uint8)[None, :]
    atlas = build_mipmaps(ramp)
    x0, x1 = 1.0, 9.0  # strip along world x, texture s from 16 to 240
    s0, s1 = 16.0, 240.0
    corners = np.array([[x0, -1.5, 0.0], [x1, -1.5, 0.0], [x1, 1.5, 0.0], [x0, 1.5, 0.0]])
    uv = np.array([[s0, 0.0], [s1, 0.0], [s1, 40.0], [s0, 40.0]])
    T = _pose(np.array([0.0, 0.0, 1.0]), 0.0, 0.25)
    out = _render(_mesh([(*_quad_tris(corners, uv), 1)]), atlas, T)
    centre, d = _rays_world(T)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(d[..., 2] < 0, -centre[2] / d[..., 2], np.inf)
    x_hit = centre[0] + z * d[..., 0]
    s_true = s0 + (x_hit - x0) / (x1 - x0) * (s1 - s0)
    ok = (out.instance == 1) & (s_true > s0 + 8) & (s_true < s1 - 8)
    assert ok.sum() > 500
    assert out.color is not None
    np.testing.assert_allclose(out.color[ok][:, 0] * 255.0, s_true[ok] - 0.5, atol=0.75)


def test_high_frequency_texture_is_filtered_not_aliased() -> None:
    """A one-texel checkerboard on a wall far enough that each pixel spans ~6 texels:
    mipmapping gives nearly the mean grey everywhere (no moire), and a sub-pixel camera
    shift changes the image by almost nothing."""
    checker = ((np.indices((128, 128)).sum(axis=0) % 2) * 255).astype(np.uint8)
    atlas = build_mipmaps(np.repeat(checker[None, :, :, None], 3, axis=3))
    z = 6.0
    corners = np.array([[-3, -3, z], [3, -3, z], [3, 3, z], [-3, 3, z]])
    uv = np.array([[0, 0], [600, 0], [600, 600], [0, 600]], dtype=float)  # 100 texels/m
    mesh = _mesh([(*_quad_tris(corners, uv), 1)])
    a = _render(mesh, atlas, sample_color=False)
    T_shift = np.eye(4)
    T_shift[0, 3] = 0.3 * z / K[0]  # 0.3 pixel
    b = _render(mesh, atlas, T_shift, sample_color=False)
    assert a.texel_gray is not None and b.texel_gray is not None
    both = (a.instance == 1) & (b.instance == 1)
    assert np.abs(a.texel_gray[both] - 0.5).max() < 0.02
    assert np.abs(a.texel_gray[both] - b.texel_gray[both]).max() < 0.02


def test_thermal_request_skips_colour_and_matches_full_render() -> None:
    """Asking for depth, material and luma only (the thermal pass) returns no colour,
    and the same depth, material and luma as a full render; with no texture request at
    all, only the geometric images are returned."""
    rng = np.random.default_rng(9)
    atlas = build_mipmaps(rng.integers(0, 256, (1, 32, 32, 3), dtype=np.uint8))
    mesh = _mesh([_floor(20.0)])
    T = _pose(np.array([0.0, 0.0, 1.3]), 0.4, 0.3)
    full = _render(mesh, atlas, T)
    thermal = _render(mesh, atlas, T, sample_color=False)
    geo = _render(mesh, atlas, T, sample_color=False, sample_gray=False)
    assert thermal.color is None and thermal.texel_gray is not None
    assert geo.color is None and geo.texel_gray is None
    assert full.texel_gray is not None
    np.testing.assert_array_equal(thermal.depth, full.depth)
    np.testing.assert_array_equal(thermal.material, full.material)
    np.testing.assert_array_equal(thermal.texel_gray, full.texel_gray)
    np.testing.assert_array_equal(geo.depth, full.depth)


def test_backface_culling_is_optional() -> None:
    """A triangle whose corners appear clockwise (normal away from the camera) is drawn
    by default (walls seen from both sides) and dropped with ``cull_backfaces``."""
    front = np.array([[[-0.5, -0.5, 2.0], [-0.5, 0.5, 2.0], [0.5, 0.0, 2.0]]])
    # counter-clockwise seen from the camera (y down): normal (p1-p0)x(p2-p0) along -z
    n = np.cross(front[0, 1] - front[0, 0], front[0, 2] - front[0, 0])
    assert n[2] < 0
    back = front[:, ::-1].copy()
    atlas = _flat_atlas()
    uv = np.zeros((1, 3, 2))
    for tri, drawn_when_culling in [(front, True), (back, False)]:
        mesh = _mesh([(tri, uv, 1)])
        assert (_render(mesh, atlas).instance == 1).sum() > 100
        culled = _render(mesh, atlas, cull_backfaces=True).instance == 1
        assert culled.any() == drawn_when_culling


def test_edge_on_triangle_through_camera_centre_draws_nothing() -> None:
    """A triangle whose plane contains the camera centre projects to a line: it is
    skipped (no pixels, no division by zero) while a normal quad behind it still draws."""
    edge_on = np.array([[[0.0, -1.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, 5.0]]])
    wall = _quad_tris(np.array([[-20, -20, 6.0], [20, -20, 6.0], [20, 20, 6.0], [-20, 20, 6.0]]))
    out = _render(_mesh([(edge_on, np.zeros((1, 3, 2)), 1), (*wall, 2)]), _flat_atlas())
    assert not np.any(out.instance == 1)
    assert np.all(out.instance == 2)
    assert np.all(np.isfinite(out.depth))


def test_beyond_far_and_empty_scene_render_nothing() -> None:
    """A quad at 25 m with far = 20 m, and an empty mesh, both give all-zero images."""
    atlas = _flat_atlas()
    q = _quad_tris(np.array([[-9, -9, 25.0], [9, -9, 25.0], [9, 9, 25.0], [-9, 9, 25.0]]))
    empty = Mesh(
        np.zeros((0, 3, 3)),
        np.zeros((0, 3, 2)),
        np.zeros(0, np.int32),
        np.zeros(0, np.uint16),
        np.zeros(0, np.uint16),
        np.zeros(0, np.float32),
    )
    for mesh in (_mesh([(*q, 1)]), empty):
        out = _render(mesh, atlas, far=20.0)
        assert out.color is not None and out.texel_gray is not None
        for img in (out.depth, out.instance, out.material, out.color, out.texel_gray):
            assert not img.any()


def test_mip_pyramid_levels_are_box_means() -> None:
    """Level 0 round-trips the texture; level L is the rounded mean of 2^L blocks; the
    4th channel is the luma; sizes below the 4x4 tile read back correctly."""
    rng = np.random.default_rng(10)
    tex = rng.integers(0, 256, (2, 16, 16, 3), dtype=np.uint8)
    atlas = build_mipmaps(tex)
    assert atlas.n_levels == 5 and atlas.size == 16 and atlas.n_textures == 2
    for t in range(2):
        np.testing.assert_array_equal(atlas.level(t, 0)[..., :3], tex[t])
        for lev in range(1, 5):
            s = 16 >> lev
            block = tex[t].astype(float).reshape(s, 16 // s, s, 16 // s, 3).mean(axis=(1, 3))
            got = atlas.level(t, lev)
            assert got.shape == (s, s, 4)
            assert np.abs(got[..., :3] - block).max() <= 0.5
            assert np.abs(got[..., 3] - block @ np.array([0.299, 0.587, 0.114])).max() <= 0.5 + 1e-9


def test_bad_inputs_raise_geometry_error() -> None:
    """Malformed textures, meshes, intrinsics, clip distances, transforms and texture
    indices are rejected with GeometryError naming the problem."""
    with pytest.raises(GeometryError, match="power-of-two"):
        build_mipmaps(np.zeros((1, 12, 12, 3), dtype=np.uint8))
    with pytest.raises(GeometryError, match="uint8"):
        build_mipmaps(np.zeros((1, 16, 16, 3), dtype=np.float32))
    tris, uv = _quad_tris(np.eye(4, 3))
    zeros = np.zeros(2, dtype=int)
    with pytest.raises(GeometryError, match=r"Mesh\.uv: expected shape"):
        Mesh(tris, uv[:, :2], zeros, zeros, zeros, np.ones(2))
    with pytest.raises(GeometryError, match="non-finite"):
        Mesh(np.full((2, 3, 3), np.nan), uv, zeros, zeros, zeros, np.ones(2))
    with pytest.raises(GeometryError, match=r"Mesh\.instance: values outside"):
        Mesh(tris, uv, zeros, np.full(2, -1), zeros, np.ones(2))
    with pytest.raises(GeometryError, match=r"Mesh\.texture: expected an integer dtype"):
        Mesh(tris, uv, np.zeros(2), zeros, zeros, np.ones(2))
    mesh = _mesh([(tris, uv, 1)], texture=3)
    atlas = _flat_atlas()
    with pytest.raises(GeometryError, match="outside the atlas"):
        _render(mesh, atlas)
    ok = _mesh([(tris, uv, 1)])
    with pytest.raises(GeometryError, match="fx, fy > 0"):
        render(ok, atlas, (0.0, 100.0, 10.0, 10.0), W, H, np.eye(4))
    with pytest.raises(GeometryError, match="near < far"):
        _render(ok, atlas, far=0.05)
    with pytest.raises(GeometryError, match="T_camera_world"):
        _render(ok, atlas, np.eye(4) * 2)
