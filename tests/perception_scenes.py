"""Synthetic scenes with known ground truth for the perception tests: a pinhole camera,
boxes rendered by exact ray casting, a corridor, a room and doors on a wall."""

from __future__ import annotations

import numpy as np

from wardmap.server.perception.masks import box_of_mask
from wardmap.server.perception.types import Instance
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import yaw_transform

CAMERA = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
"""The colour camera of every scene: 320 x 240, 262.5 px focal length."""
BGR = np.random.default_rng(3).integers(0, 256, (CAMERA.height, CAMERA.width, 3), dtype=np.uint8)
"""A random colour image of the camera's size (texture for ORB and the colour histogram)."""


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_world_camera of a camera at ``eye`` looking at ``target`` (world z up, no roll)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


def render_box(T_world_camera: np.ndarray, T_world_box: np.ndarray, size: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) float32 and hit mask of an oriented box, by exact ray/slab intersection."""
    rays_c = CAMERA.pixel_rays().reshape(-1, 3)  # z = 1, so the ray parameter is the depth
    T_box_cam = np.linalg.inv(T_world_box) @ T_world_camera
    origin = T_box_cam[:3, 3]
    dirs = rays_c @ T_box_cam[:3, :3].T
    half = size / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - origin) / dirs
        t2 = (half - origin) / dirs
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (t_near <= t_far) & (t_near > 0)
    depth = np.where(hit, t_near, 0.0).astype(np.float32).reshape(CAMERA.height, CAMERA.width)
    return depth, hit.reshape(CAMERA.height, CAMERA.width)


def corridor_depth(wall_m: float = 3.0) -> np.ndarray:
    """Depth (H, W) of a camera 1.05 m above the floor looking level at a wall ``wall_m`` ahead:
    the wall, and the floor in the rows whose ray meets it first."""
    rows = (np.arange(CAMERA.height) - CAMERA.cy) / CAMERA.fy
    with np.errstate(divide="ignore"):
        floor = np.where(rows > 0, 1.05 / rows, np.inf)
    depth = np.minimum(floor, wall_m)[:, None] * np.ones((1, CAMERA.width))
    return depth.astype(np.float32)


def room_depth(wall_m: float = 4.0, ceiling_m: float = 2.6) -> np.ndarray:
    """Depth (H, W) of the camera of ``T_LEVEL`` (1.05 m up, looking level) at a wall ``wall_m``
    ahead, with the floor and a ceiling ``ceiling_m`` high where their rays meet them first."""
    rows = (np.arange(CAMERA.height) - CAMERA.cy) / CAMERA.fy
    with np.errstate(divide="ignore"):
        floor = np.where(rows > 0, 1.05 / rows, np.inf)
        ceiling = np.where(rows < 0, (ceiling_m - 1.05) / -rows, np.inf)
    depth = np.minimum(np.minimum(floor, ceiling), wall_m)[:, None] * np.ones((1, CAMERA.width))
    return depth.astype(np.float32)


T_LEVEL = look_at(np.array([0.0, 0.0, 1.05]), np.array([3.0, 0.0, 1.05]))


def box_instance(category: str, rows: slice, cols: slice) -> Instance:
    m = np.zeros((CAMERA.height, CAMERA.width), bool)
    m[rows, cols] = True
    return Instance(category, 0.9, m, box_of_mask(m))


def render_doors_on_a_wall(T_world_camera: np.ndarray, door_x: tuple[float, ...]
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth (H, W), door index per pixel (0 = wall, k = door k) and world points (H, W, 3) of
    1.16 x 2.18 m doors centred at ``door_x`` in front of a wall at y = 3.1 m."""
    depth, _ = render_box(T_world_camera, yaw_transform(6.0, 3.15, 0.0, z=1.25), np.array([14.0, 0.1, 2.5]))
    label = np.zeros(depth.shape, int)
    for k, x in enumerate(door_x, 1):
        d, hit = render_box(T_world_camera, yaw_transform(x, 3.07, 0.0, z=1.09), np.array([1.16, 0.06, 2.18]))
        near = hit & ((depth == 0) | (d < depth))
        depth[near], label[near] = d[near], k
    points = (CAMERA.pixel_rays() * depth[..., None]) @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
    return depth, label, points
