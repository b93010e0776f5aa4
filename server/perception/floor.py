"""Floor checks: instances of floor-standing classes that cannot be what the segmenter says,
given where they lie relative to the floor.

A segmentation network sometimes names a thing of another kind after a floor-standing
class. Where the floor is known (a robot base whose frame sits on the floor), three checks
leave such instances out, in this order (:func:`drop_misplaced`):

1. :func:`floating_above_floor` (``PerceptionConfig.floor_gap_m``): the instance ends in
   mid-air with free space below it (a red fire extinguisher on the wall taken for a chair);
2. :func:`part_of_taller_surface` (``PerceptionConfig.max_top_m``): its pixels lie on a
   surface that rises, unbroken, higher than any object of the class (a strip of corridor
   wall at the image border taken for a cabinet);
3. :func:`flat_on_floor` (``PerceptionConfig.min_top_m``): its top is lower than any object
   of the class reaches (the dark gap under a bed's footboard taken for a cart).

Each check flags every instance on its own (its mask, the depth, the camera pose and the
floor; no instance looks at another), so the checks commute with any other per-instance
filter and with each other.

The floor's height comes from the robot base: :func:`floor_under` for a data set (camera
pose and the base-to-camera calibration); ``keyframe.keyframe_floor_z`` for a keyframe on
the wire (its wheel-odometry base pose).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.masks import Mask, fit_inverse_depth_plane
from wardmap.server.perception.types import Instance
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import GeometryError

__all__ = [
    "LeftOut",
    "drop_floating",
    "drop_floor_pieces",
    "drop_misplaced",
    "drop_wall_pieces",
    "flat_on_floor",
    "floating_above_floor",
    "floor_under",
    "part_of_taller_surface",
]


def floor_under(T_world_camera: NDArray[np.float64], T_base_camera: NDArray[np.float64]) -> float:
    """Height (metres, world z) of the floor under a camera on a robot base whose frame sits on
    the floor (``T_base_camera``: the camera in the base frame): the ``floor_z_m`` of
    :func:`drop_floating`."""
    return float((np.asarray(T_world_camera) @ np.linalg.inv(T_base_camera))[2, 3])


class LeftOut(NamedTuple):
    """How many instances :func:`drop_misplaced` left out, by check."""

    floating: int
    """Floating above the floor (``floor_gap_m``)."""
    walls: int
    """A piece of a surface taller than any object of the class (``max_top_m``)."""
    floors: int
    """Flat on the floor, lower than any object of the class (``min_top_m``)."""


def drop_misplaced(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                   config: PerceptionConfig, T_world_camera: NDArray[np.float64],
                   floor_z_m: float | None) -> tuple[list[Instance], LeftOut]:
    """``instances`` after the three floor checks (:func:`drop_floating`,
    :func:`drop_wall_pieces`, :func:`drop_floor_pieces`, in that order), and how many each left
    out. ``floor_z_m`` as for :func:`drop_floating`; None keeps every instance."""
    kept, floating = drop_floating(instances, depth_m, camera, config, T_world_camera, floor_z_m)
    kept, walls = drop_wall_pieces(kept, depth_m, camera, config, T_world_camera, floor_z_m)
    kept, floors = drop_floor_pieces(kept, depth_m, camera, config, T_world_camera, floor_z_m)
    return kept, LeftOut(floating, walls, floors)


def drop_floating(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                  config: PerceptionConfig, T_world_camera: NDArray[np.float64],
                  floor_z_m: float | None) -> tuple[list[Instance], int]:
    """``instances`` without those of the ``floor_gap_m`` classes that float above the floor
    (:func:`floating_above_floor`), and how many were
    left out. ``floor_z_m``: the floor's height in the frame of ``T_world_camera`` (world z
    up), metres; None (floor unknown: a hand-held camera) keeps every instance."""
    return _drop(instances, floor_z_m, config.floor_gap_m, lambda floor, table: floating_above_floor(
        instances, depth_m, camera, T_world_camera, floor_z_m=floor, max_gap_m=table))


def drop_wall_pieces(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                     config: PerceptionConfig, T_world_camera: NDArray[np.float64],
                     floor_z_m: float | None) -> tuple[list[Instance], int]:
    """``instances`` without those of the ``max_top_m`` classes that are a piece of a taller
    surface (:func:`part_of_taller_surface`), and how
    many were left out. ``floor_z_m`` as for :func:`drop_floating`; None keeps every instance."""
    return _drop(instances, floor_z_m, config.max_top_m, lambda floor, table: part_of_taller_surface(
        instances, depth_m, camera, T_world_camera, floor_z_m=floor, max_top_m=table))


def drop_floor_pieces(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                      config: PerceptionConfig, T_world_camera: NDArray[np.float64],
                      floor_z_m: float | None) -> tuple[list[Instance], int]:
    """``instances`` without those of the ``min_top_m`` classes that lie flat on the floor
    (:func:`flat_on_floor`), and how many were left out.
    ``floor_z_m`` as for :func:`drop_floating`; None keeps every instance."""
    return _drop(instances, floor_z_m, config.min_top_m, lambda floor, table: flat_on_floor(
        instances, depth_m, camera, T_world_camera, floor_z_m=floor, min_top_m=table))


def _drop(instances: Sequence[Instance], floor_z_m: float | None, pairs: Sequence[tuple[str, float]],
          flags: Callable[[float, dict[str, float]], list[bool]]) -> tuple[list[Instance], int]:
    """The instances ``flags`` (called with the floor height and the ``[class, value]`` ``pairs``
    as a dict) does not flag, and how many it flagged; every instance when the floor is unknown
    or ``pairs`` is empty."""
    if floor_z_m is None or not pairs or not instances:
        return list(instances), 0
    return _without(instances, flags(floor_z_m, dict(pairs)))


def _without(instances: Sequence[Instance], flags: Sequence[bool]) -> tuple[list[Instance], int]:
    """The instances whose flag is False, and how many were flagged."""
    kept = [inst for inst, flagged in zip(instances, flags, strict=True) if not flagged]
    return kept, len(instances) - len(kept)


def floating_above_floor(
    instances: Sequence[Instance],
    depth_m: NDArray[np.float32],
    camera: PinholeCamera,
    T_world_camera: ArrayLike,
    *,
    floor_z_m: float,
    max_gap_m: Mapping[str, float],
    up: ArrayLike = (0.0, 0.0, 1.0),
    occluder_m: float = 0.15,
    band_px: tuple[int, int] = (2, 8),
    open_fraction: float = 0.5,
) -> list[bool]:
    """Which instances of floor-standing classes float: their lowest part is more than the
    class's ``max_gap_m`` above the floor and nothing hides what lies below them.

    A chair stands on the floor. A "chair" whose bottom is 0.65 m up a wall, with the wall
    visible right below it, is something else: a red fire extinguisher taken for a red chair.

    The bottom height (metres above ``floor_z_m`` along ``up``) is the 10th percentile over
    the mask's columns of the ray through the column's lowest mask pixel, taken at the
    instance's median depth: chair legs without depth still reach the floor, and a mask
    nearer at the bottom than its median (an object seen lengthwise) comes out lower, not
    higher.
    For each column, the valid depth ``band_px`` rows below its lowest mask pixel tells
    whether the view below is *hidden* (an occluder more than ``occluder_m`` nearer than
    the instance's median depth, or the mask reaches the image's last rows) or *open*
    (the wall or floor at or behind the instance). An instance floats when its bottom is
    above the gap and at least ``open_fraction`` of the columns with depth below are open.

    Args:
        instances: instances of one colour image (H, W).
        depth_m: float32 (H, W) depth, metres, registered to the colour image; 0 = none.
        camera: the colour camera.
        T_world_camera: (4, 4) camera pose in a world frame whose floor is the plane
            ``up . x = floor_z_m``.
        floor_z_m: floor height along ``up`` in that frame, metres.
        max_gap_m: class -> largest height of its lowest point above the floor (metres);
            classes not in it never float.
        up: (3,) world up (``-gravity_world``).

    Returns:
        One flag per instance, in order (False for instances without 20 depth pixels).
    """
    lo, hi = band_px
    if not (occluder_m >= 0 and 0 <= lo < hi and 0 < open_fraction <= 1):
        raise GeometryError("floating_above_floor: need occluder_m >= 0, 0 <= band_px[0] < band_px[1], "
                            "0 < open_fraction <= 1")
    h_axis, h_zero = _height_above_floor(T_world_camera, up, floor_z_m, "floating_above_floor")
    depth = np.asarray(depth_m, dtype=np.float32)
    H = depth.shape[0]
    out: list[bool] = []
    for inst in instances:
        gap = max_gap_m.get(inst.category)
        if gap is None:
            out.append(False)
            continue
        ys, xs = np.nonzero(inst.mask)
        seen = _with_depth(ys, xs, depth)
        if seen is None:
            out.append(False)
            continue
        z_obj = float(np.median(seen[2]))
        cols = np.unique(xs)
        lowest = np.full(inst.mask.shape[1], -1, dtype=np.int64)
        np.maximum.at(lowest, xs, ys)
        y_low = lowest[cols]
        rays = camera.unproject(np.stack([cols, y_low], axis=1), np.full(len(cols), z_obj))
        if float(np.percentile(rays @ h_axis + h_zero, 10)) <= gap:
            out.append(False)
            continue
        rows = y_low[:, None] + np.arange(lo, hi)[None, :]
        inside = rows < H
        below = np.where(inside, depth[np.minimum(rows, H - 1), cols[:, None]], 0.0)
        below = np.where(np.isfinite(below) & (below > 0), below, np.nan)
        known = ~np.all(np.isnan(below), axis=1)
        at_edge = y_low + lo >= H - 1  # cut by the image: the band starts at its last row or past it
        hidden = at_edge.copy()
        if known.any():
            near = np.nanmedian(below[known], axis=1) < z_obj - occluder_m
            hidden[np.flatnonzero(known)[near]] = True
        n_open = int(np.sum(known & ~hidden))
        n_known = int(np.sum(known | at_edge))
        out.append(n_known > 0 and n_open >= open_fraction * n_known)
    return out


def part_of_taller_surface(
    instances: Sequence[Instance],
    depth_m: NDArray[np.float32],
    camera: PinholeCamera,
    T_world_camera: ArrayLike,
    *,
    floor_z_m: float,
    max_top_m: Mapping[str, float],
    up: ArrayLike = (0.0, 0.0, 1.0),
    margin_m: float = 0.3,
    step_m: float = 0.05,
    step_relative: float = 0.02,
    on_share: float = 0.5,
    tolerance_m: float = 0.03,
    tolerance_relative: float = 0.01,
    max_samples: int = 600,
    iterations: int = 48,
    seed: int = 0,
) -> list[bool]:
    """Which instances of floor-standing classes are a piece of a taller surface: the surface
    goes on, unbroken, above the mask's top to higher than any object of the class, and most
    of the mask lies on that surface's plane.

    A cabinet ends at its top, and above it the camera sees the wall behind, a step away in
    depth. A "cabinet" that is a strip of corridor wall cut by the image border (the network
    does this now and then) goes on above its mask up to the ceiling, in one plane with the
    mask. In each column of the mask the walk starts 2 px inside the mask's top pixel (past
    the mixed depth at its border) and climbs row by row while the depth changes by at most
    ``max(step_m, step_relative * z)`` between neighbouring rows; the climb's end is taken at
    its depth and put in the world. The surface rises too high when the median over columns of
    that height above the floor exceeds the class's ``max_top_m`` plus ``margin_m``. Then a
    plane (affine in inverse depth, as in :func:`off_background_planes`) is fitted by RANSAC
    to the climbed pixels above the mask (at most ``max_samples``, a seeded subset), and the
    instance is a piece of that surface when at least ``on_share`` of its pixels with depth
    lie on the plane (within ``max(tolerance_m, tolerance_relative * z)``). A low cabinet
    against a wall goes on into the wall above it too, but only its back edge lies in the
    wall's plane. A cabinet whose mask stops short of its top is climbed up to its real top,
    where the step to the wall behind it ends the climb. Doors are no such class: a door is
    flush with the wall that goes on above it.

    Args:
        instances: instances of one colour image (H, W).
        depth_m: float32 (H, W) depth, metres, registered to the colour image; 0 = none.
        camera: the colour camera.
        T_world_camera: (4, 4) camera pose in a world frame whose floor is the plane
            ``up . x = floor_z_m``.
        floor_z_m: floor height along ``up`` in that frame, metres.
        max_top_m: class -> height above the floor (metres) that no object of the class
            reaches; classes not in it are never flagged.
        up: (3,) world up (``-gravity_world``).

    Returns:
        One flag per instance, in order (False when fewer than 3 columns have depth at their
        start, the climb leaves fewer than 50 pixels, or no plane is found).
    """
    if not (margin_m >= 0 and step_m > 0 and step_relative >= 0 and 0 < on_share <= 1
            and tolerance_m > 0 and tolerance_relative >= 0 and max_samples >= 3 and iterations >= 1):
        raise GeometryError("part_of_taller_surface: need margin_m >= 0, step_m > 0, step_relative >= 0, "
                            "0 < on_share <= 1, tolerance_m > 0, tolerance_relative >= 0, "
                            "max_samples >= 3, iterations >= 1")
    h_axis, h_zero = _height_above_floor(T_world_camera, up, floor_z_m, "part_of_taller_surface")
    depth = np.asarray(depth_m, dtype=np.float32)
    out: list[bool] = []
    for inst in instances:
        top_m = max_top_m.get(inst.category)
        out.append(top_m is not None and _on_taller_surface(
            inst.mask, depth, camera, h_axis, h_zero, top_m + margin_m, step_m, step_relative, on_share,
            tolerance_m, tolerance_relative, max_samples, iterations, seed))
    return out


def _on_taller_surface(mask: Mask, depth: NDArray[np.float32], camera: PinholeCamera,
                       h_axis: NDArray[np.float64], h_zero: float, limit_m: float, step_m: float,
                       step_relative: float, on_share: float, tolerance_m: float, tolerance_relative: float,
                       max_samples: int, iterations: int, seed: int) -> bool:
    """:func:`part_of_taller_surface` for one mask; ``limit_m``: the class's top plus the margin."""
    H = mask.shape[0]
    cols = np.flatnonzero(mask.any(axis=0))
    top = np.argmax(mask[:, cols], axis=0)  # first mask row of each column
    start = np.minimum(top + 2, H - 1)
    z = depth[start, cols].astype(np.float64)
    ok = np.isfinite(z) & (z > 0) & (top > 0)  # a mask at the image's top row cannot be climbed
    cols, top, start, z = cols[ok], top[ok], start[ok], z[ok]
    if cols.size < 3:
        return False
    reach = start.copy()
    climbing = np.ones(cols.size, dtype=bool)
    for r in range(int(start.max()) - 1, -1, -1):
        act = climbing & (r < reach)
        if not act.any():
            break
        zr = depth[r, cols].astype(np.float64)
        on = act & np.isfinite(zr) & (zr > 0) & (np.abs(zr - z) <= np.maximum(step_m, step_relative * z))
        climbing[act & ~on] = False
        reach[on] = r
        z[on] = zr[on]
    ends = camera.unproject(np.stack([cols, reach], axis=1), z)
    if float(np.median(ends @ h_axis + h_zero)) <= limit_m:
        return False
    above = [(np.arange(a, t), np.full(t - a, c)) for a, t, c in zip(reach, top, cols, strict=True) if t > a]
    if not above:
        return False
    rr = np.concatenate([a for a, _ in above])
    cc = np.concatenate([c for _, c in above])
    if rr.size < 50:
        return False
    rng = np.random.default_rng(seed)
    if rr.size > max_samples:
        keep = rng.choice(rr.size, size=max_samples, replace=False)
        rr, cc = rr[keep], cc[keep]
    zs = depth[rr, cc].astype(np.float64)
    coef, _ = fit_inverse_depth_plane(cc.astype(np.float64), rr.astype(np.float64), zs,
                                       np.maximum(tolerance_m, tolerance_relative * zs), rng, iterations)
    if coef is None:
        return False
    mr, mc = np.nonzero(mask & (depth > 0))
    if mr.size == 0:
        return False
    zm = depth[mr, mc].astype(np.float64)
    wp = coef[0] * mc + coef[1] * mr + coef[2]
    on_plane = (wp > 0) & (np.abs(1.0 / np.where(wp > 0, wp, 1.0) - zm)
                           <= np.maximum(tolerance_m, tolerance_relative * zm))
    return bool(on_plane.mean() >= on_share)


def flat_on_floor(
    instances: Sequence[Instance],
    depth_m: NDArray[np.float32],
    camera: PinholeCamera,
    T_world_camera: ArrayLike,
    *,
    floor_z_m: float,
    min_top_m: Mapping[str, float],
    up: ArrayLike = (0.0, 0.0, 1.0),
    top_percentile: float = 90.0,
    edge_px: int = 2,
) -> list[bool]:
    """Which instances of floor-standing classes lie flat on the floor: their top is less than
    the class's ``min_top_m`` above the floor.

    A cart is about a metre tall. A "cart" 6 cm tall along the floor is the dark gap under a
    bed's footboard, which the network calls a cart now and then. The top is the
    ``top_percentile`` of the heights above the floor of the mask's pixels with depth. A mask
    that reaches within ``edge_px`` of the image's top row may go on above the view and is
    never flagged. An occluder above the mask
    is no reason to keep it: what shows under a bed's footboard or a desk's front panel that
    low is no more than the feet of an object, and the gap under a footboard is nearer the
    floor than the footboard itself.

    Args:
        instances: instances of one colour image (H, W).
        depth_m: float32 (H, W) depth, metres, registered to the colour image; 0 = none.
        camera: the colour camera.
        T_world_camera: (4, 4) camera pose in a world frame whose floor is the plane
            ``up . x = floor_z_m``.
        floor_z_m: floor height along ``up`` in that frame, metres.
        min_top_m: class -> height above the floor (metres) that every object of the class
            reaches; classes not in it are never flagged.
        up: (3,) world up (``-gravity_world``).

    Returns:
        One flag per instance, in order (False for instances without 20 depth pixels).
    """
    if not (0 < top_percentile <= 100 and edge_px >= 0):
        raise GeometryError("flat_on_floor: need 0 < top_percentile <= 100 and edge_px >= 0")
    h_axis, h_zero = _height_above_floor(T_world_camera, up, floor_z_m, "flat_on_floor")
    depth = np.asarray(depth_m, dtype=np.float32)
    out: list[bool] = []
    for inst in instances:
        least = min_top_m.get(inst.category)
        if least is None or inst.mask[: edge_px + 1].any():
            out.append(False)
            continue
        ys, xs = np.nonzero(inst.mask)
        seen = _with_depth(ys, xs, depth)
        if seen is None:
            out.append(False)
            continue
        ys, xs, z = seen
        points = camera.unproject(np.stack([xs, ys], axis=1), z.astype(np.float64))
        out.append(float(np.percentile(points @ h_axis + h_zero, top_percentile)) < least)
    return out


def _height_above_floor(T_world_camera: ArrayLike, up: ArrayLike, floor_z_m: float,
                        who: str) -> tuple[NDArray[np.float64], float]:
    """``(h_axis, h_zero)``: the height above the floor of camera-frame points p (N, 3), metres,
    is ``p @ h_axis + h_zero`` (``up . (R p + t) - floor_z_m``).

    Raises:
        GeometryError: not a (4, 4) pose or not a (3,) non-zero up vector (``who`` names the caller).
    """
    T = np.asarray(T_world_camera, dtype=np.float64)
    u = np.asarray(up, dtype=np.float64).reshape(-1)
    if T.shape != (4, 4) or u.shape != (3,) or not np.linalg.norm(u) > 0:
        raise GeometryError(f"{who}: need a (4, 4) pose and a (3,) non-zero up vector, "
                            f"got {T.shape}, {u.shape}")
    u = u / np.linalg.norm(u)
    return T[:3, :3].T @ u, float(u @ T[:3, 3]) - floor_z_m


def _with_depth(ys: NDArray[np.intp], xs: NDArray[np.intp], depth: NDArray[np.float32], least: int = 20
                ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float32]] | None:
    """Rows, columns and depths (N,) of the pixels (``ys``, ``xs``: a mask's ``np.nonzero``) that have
    depth; None when fewer than ``least``."""
    z = depth[ys, xs]
    has = np.isfinite(z) & (z > 0)
    if int(has.sum()) < least:
        return None
    return ys[has], xs[has], z[has]
