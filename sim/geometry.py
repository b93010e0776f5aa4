"""Triangle soup of the simulated world: boxes and quads with textures and materials.

World frame: metres, z up, the floor at z = 0. A :class:`TriangleSoup` is what the
rasterizer draws; it is built from box :class:`Part` s placed with ``T_world_*``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wardmap.sim.textures import TEXTURE_SIZE

F64 = NDArray[np.float64]

# Overhead-ish light for Lambert shading (unit vector towards the light, world frame).
_LIGHT_DIR = np.array([0.25, 0.35, 1.0]) / np.linalg.norm([0.25, 0.35, 1.0])
_AMBIENT = 0.55


@dataclass(frozen=True)
class Part:
    """One box of an object model, in the model's frame (x forward, y left, z up).

    Attributes:
        center: box centre (3,) in metres in the model frame.
        size: edge lengths (3,) along the box's own axes, metres.
        texture: texture name in the world's :class:`~wardmap.sim.textures.TextureBank`.
        material: material name (:mod:`wardmap.sim.materials`).
        texels_per_m: texture density; 0 stretches the texture over each face.
        yaw, pitch: rotation of the box about z then y (radians), for limbs and wheels.
    """

    center: tuple[float, float, float]
    size: tuple[float, float, float]
    texture: str
    material: str
    texels_per_m: float = 0.0
    yaw: float = 0.0
    pitch: float = 0.0


@dataclass(frozen=True)
class TriangleSoup:
    """Triangles with per-triangle attributes (T triangles).

    Attributes:
        vertices: (T, 3, 3) float64 corners in the world frame, metres.
        uv: (T, 3, 2) float32 texture coordinates in texels (wrap around).
        texture: (T,) int32 texture ids.
        instance: (T,) uint16 object instance ids, 0 for none.
        material: (T,) uint16 material ids.
        shade: (T,) float32 Lambert factor 0..1 (view independent).
    """

    vertices: NDArray[np.float64]
    uv: NDArray[np.float32]
    texture: NDArray[np.int32]
    instance: NDArray[np.uint16]
    material: NDArray[np.uint16]
    shade: NDArray[np.float32]

    @staticmethod
    def empty() -> TriangleSoup:
        return TriangleSoup(
            np.zeros((0, 3, 3)),
            np.zeros((0, 3, 2), np.float32),
            np.zeros(0, np.int32),
            np.zeros(0, np.uint16),
            np.zeros(0, np.uint16),
            np.zeros(0, np.float32),
        )

    def __len__(self) -> int:
        return int(self.vertices.shape[0])

    def select(self, keep: NDArray[np.bool_]) -> TriangleSoup:
        """The triangles where ``keep`` (T,) is True, in their order."""
        return TriangleSoup(
            self.vertices[keep], self.uv[keep], self.texture[keep], self.instance[keep], self.material[keep],
            self.shade[keep],
        )

    @staticmethod
    def concat(parts: list[TriangleSoup]) -> TriangleSoup:
        parts = [p for p in parts if len(p)]
        if not parts:
            return TriangleSoup.empty()
        return TriangleSoup(
            np.concatenate([p.vertices for p in parts]),
            np.concatenate([p.uv for p in parts]),
            np.concatenate([p.texture for p in parts]),
            np.concatenate([p.instance for p in parts]),
            np.concatenate([p.material for p in parts]),
            np.concatenate([p.shade for p in parts]),
        )


def _rot_zy(yaw: float, pitch: float) -> F64:
    cz, sz, cy, sy = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    return Rz @ Ry


# Unit cube faces: (normal axis, sign) -> 4 corners (counter-clockwise seen from outside)
# and the two in-face axes used for texture coordinates (u axis, v axis).
_FACES = []
for _axis in range(3):
    for _sign in (-1.0, 1.0):
        _u = (_axis + 1) % 3
        _v = (_axis + 2) % 3
        if _axis != 2:  # vertical faces: v runs along z (up) so textures stand upright
            _u, _v = next(a for a in range(3) if a not in (_axis, 2)), 2
        _FACES.append((_axis, _sign, _u, _v))


def box_soup(
    T_world_box: F64,
    size: tuple[float, float, float] | F64,
    texture: int,
    material: int,
    instance: int,
    texels_per_m: float = 0.0,
) -> TriangleSoup:
    """Twelve triangles of a box of ``size`` (metres) centred at the origin of ``T_world_box``.

    Texture: stretched over each face when ``texels_per_m`` is 0, else tiled at that
    density; on vertical faces the texture's rows run top to bottom (v grows downward).
    """
    s = np.asarray(size, np.float64) / 2.0
    R, t = T_world_box[:3, :3], T_world_box[:3, 3]
    verts, uvs, shades = [], [], []
    S = float(TEXTURE_SIZE)
    for axis, sign, ua, va in _FACES:
        corners = []
        for cu, cv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            p = np.zeros(3)
            p[axis] = sign * s[axis]
            p[ua] = cu * s[ua]
            p[va] = cv * s[va]
            corners.append(p)
        c = np.array(corners) @ R.T + t
        if texels_per_m > 0:
            uv = np.array(
                [
                    [(cu + 1) * s[ua] * texels_per_m, (1 - cv) * s[va] * texels_per_m]
                    for cu, cv in ((-1, -1), (1, -1), (1, 1), (-1, 1))
                ]
            )
        else:
            uv = np.array([[0.0, S], [S, S], [S, 0.0], [0.0, 0.0]])
        if sign < 0:  # mirror u so the texture reads correctly from outside
            uv[:, 0] = uv[:, 0].max() - uv[:, 0] if texels_per_m <= 0 else -uv[:, 0]
        n = np.zeros(3)
        n[axis] = sign
        shade = _AMBIENT + (1 - _AMBIENT) * max(0.0, float((R @ n) @ _LIGHT_DIR))
        verts += [c[[0, 1, 2]], c[[0, 2, 3]]]
        uvs += [uv[[0, 1, 2]], uv[[0, 2, 3]]]
        shades += [shade, shade]
    n_tri = len(verts)
    return TriangleSoup(
        np.array(verts),
        np.array(uvs, np.float32),
        np.full(n_tri, texture, np.int32),
        np.full(n_tri, instance, np.uint16),
        np.full(n_tri, material, np.uint16),
        np.array(shades, np.float32),
    )


def quad_soup(corners: F64, uv: F64, texture: int, material: int, instance: int, normal: F64) -> TriangleSoup:
    """Two triangles of a planar quad: corners (4, 3) world, uv (4, 2) texels, normal (3,)."""
    shade = _AMBIENT + (1 - _AMBIENT) * max(0.0, float(np.asarray(normal) @ _LIGHT_DIR))
    return TriangleSoup(
        np.stack([corners[[0, 1, 2]], corners[[0, 2, 3]]]),
        np.stack([uv[[0, 1, 2]], uv[[0, 2, 3]]]).astype(np.float32),
        np.full(2, texture, np.int32),
        np.full(2, instance, np.uint16),
        np.full(2, material, np.uint16),
        np.full(2, shade, np.float32),
    )


def part_transform(T_world_model: F64, part: Part) -> F64:
    """``T_world_part`` (4, 4) of a part placed in its model."""
    T = np.eye(4)
    T[:3, :3] = _rot_zy(part.yaw, part.pitch)
    T[:3, 3] = part.center
    return T_world_model @ T


def parts_bounds(parts: tuple[Part, ...]) -> tuple[F64, F64]:
    """Axis-aligned bounds (min (3,), max (3,)) of parts in the model frame."""
    pts = []
    for p in parts:
        T = part_transform(np.eye(4), p)
        s = np.asarray(p.size) / 2.0
        for dx in (-1, 1):
            for dy in (-1, 1):
                for dz in (-1, 1):
                    pts.append(T[:3, :3] @ (s * (dx, dy, dz)) + T[:3, 3])
    arr = np.array(pts)
    return arr.min(axis=0), arr.max(axis=0)
