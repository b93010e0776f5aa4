"""The floor checks (``server/perception/floor.py``) on synthetic rooms and corridors seen by a
level camera 1.05 m above the floor."""

from __future__ import annotations

import numpy as np
import pytest
from perception_scenes import (
    CAMERA,
    T_LEVEL,
    box_instance,
    corridor_depth,
    room_depth,
)

from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.floor import (
    LeftOut,
    drop_floating,
    drop_floor_pieces,
    drop_misplaced,
    drop_wall_pieces,
    flat_on_floor,
    floating_above_floor,
    floor_under,
    part_of_taller_surface,
)
from wardmap.server.perception.types import Instance
from wardmap.shared.errors import ConfigError, GeometryError


def test_a_chair_floating_on_the_wall_is_flagged() -> None:
    """A 'chair' 0.7-1.2 m up the wall, 10 cm in front of it, with the wall right below (a fire
    extinguisher the network took for a chair) floats; the same mask with a cart in front
    below it, a chair standing on the floor, a mask running down near the floor without depth
    on its lower part, a mask reaching the image's bottom rows and a door do not."""
    depth = corridor_depth()
    rows, cols = slice(106, 152), slice(150, 166)  # 0.7-1.2 m high at 2.9 m
    depth[rows, cols] = 2.9
    extinguisher = box_instance("chair", rows, cols)
    on_floor = box_instance("chair", slice(136, 230), slice(60, 111))
    standing = depth.copy()
    standing[136:230, 60:111] = 2.5  # 0.9 m tall chair at 2.5 m, its legs on the floor
    gaps = {"chair": 0.6}

    def flags(instances: list[Instance], d: np.ndarray, **kw: object) -> list[bool]:
        return floating_above_floor(instances, d, CAMERA, T_LEVEL, floor_z_m=0.0, max_gap_m=gaps, **kw)

    assert flags([extinguisher, box_instance("door", rows, cols)], depth) == [True, False]
    assert flags([on_floor], standing) == [False]
    occluded = depth.copy()
    occluded[152:212, 140:176] = 2.0  # a cart in front, below it
    assert flags([extinguisher], occluded) == [False]
    legs = depth.copy()
    legs[152:201, cols] = 0.0  # down to 0.16 m at 2.9 m, no depth there; the wall below
    assert flags([box_instance("chair", slice(106, 201), cols)], legs) == [False]
    # Cut by the image's bottom edge (0.75 m above a floor 1 m lower): it may go on below.
    bottom = depth.copy()
    bottom[106:, cols] = 2.9
    low = floating_above_floor([box_instance("chair", slice(106, CAMERA.height - 2), cols)], bottom, CAMERA,
                               T_LEVEL, floor_z_m=-1.0, max_gap_m=gaps)
    assert low == [False]
    assert floating_above_floor([box_instance("chair", slice(106, CAMERA.height - 10), cols)], bottom,
                                CAMERA, T_LEVEL, floor_z_m=-1.0, max_gap_m=gaps) == [True]
    # The same wall patch with the floor 0.2 m higher, or a larger gap, does not float either.
    assert floating_above_floor([extinguisher], depth, CAMERA, T_LEVEL, floor_z_m=0.2,
                                max_gap_m=gaps) == [False]
    assert floating_above_floor([extinguisher], depth, CAMERA, T_LEVEL, floor_z_m=0.0,
                                max_gap_m={"chair": 0.8}) == [False]
    with pytest.raises(GeometryError):
        floating_above_floor([extinguisher], depth, CAMERA, np.eye(3), floor_z_m=0.0, max_gap_m=gaps)
    with pytest.raises(GeometryError):
        flags([extinguisher], depth, open_fraction=0.0)


def test_drop_floating_needs_a_known_floor() -> None:
    depth = corridor_depth()
    depth[106:152, 150:166] = 2.9
    extinguisher = box_instance("chair", slice(106, 152), slice(150, 166))
    cfg = PerceptionConfig()
    T_base_camera = T_LEVEL.copy()  # its base at the world origin, on the floor
    raised = T_LEVEL.copy()
    raised[2, 3] += 0.4  # the same robot on a floor 0.4 m higher
    assert floor_under(T_LEVEL, T_base_camera) == pytest.approx(0.0)
    assert floor_under(raised, T_base_camera) == pytest.approx(0.4)
    assert drop_floating([extinguisher], depth, CAMERA, cfg, T_LEVEL, 0.0) == ([], 1)
    assert drop_floating([extinguisher], depth, CAMERA, cfg, T_LEVEL, None) == ([extinguisher], 0)
    off = PerceptionConfig(floor_gap_m=())
    assert drop_floating([extinguisher], depth, CAMERA, off, T_LEVEL, 0.0) == ([extinguisher], 0)
    with pytest.raises(ConfigError, match="floor_gap_m"):
        PerceptionConfig(floor_gap_m=(("chair", -0.1),))


def test_a_strip_of_wall_taken_for_a_cabinet_is_a_piece_of_a_taller_surface() -> None:
    """A 'cabinet' at the image's left border that is a strip of the wall 4 m ahead: the wall
    goes on above it into the ceiling (2.6 m), so it is flagged. A 1.9 m cabinet 0.5 m in
    front of that wall, its mask cut short of its top, its mask running onto the wall above
    it, the strip as a door, or with the floor 0.5 m higher are not."""
    depth = room_depth()
    top = {}

    def flags(instances: list[Instance], d: np.ndarray, floor_z: float = 0.0, **kw: object) -> list[bool]:
        return part_of_taller_surface(instances, d, CAMERA, T_LEVEL, floor_z_m=floor_z,
                                      max_top_m={"cabinet": 2.1}, **kw)

    strip = box_instance("cabinet", slice(130, 200), slice(0, 20))
    assert flags([strip, box_instance("door", slice(130, 200), slice(0, 20))], depth) == [True, False]
    assert flags([strip], depth, floor_z=0.5) == [False]  # the ceiling is then 2.1 m up
    cabinet = depth.copy()
    cabinet[56:199, 100:160] = 3.5  # 0-1.9 m high at 3.5 m, the wall 0.5 m behind it
    top["whole"] = box_instance("cabinet", slice(56, 199), slice(100, 160))
    top["cut short"] = box_instance("cabinet", slice(90, 199), slice(100, 160))
    top["onto the wall"] = box_instance("cabinet", slice(46, 199), slice(100, 160))
    assert flags(list(top.values()), cabinet) == [False, False, False]
    # The same region in the plane of the wall is a piece of it.
    assert flags([top["whole"]], depth) == [True]
    with pytest.raises(GeometryError):
        part_of_taller_surface([strip], depth, CAMERA, np.eye(3), floor_z_m=0.0, max_top_m={"cabinet": 2.1})
    with pytest.raises(GeometryError):
        flags([strip], depth, on_share=0.0)


def test_drop_wall_pieces_by_default_and_only_with_a_floor() -> None:
    strip = box_instance("cabinet", slice(130, 200), slice(0, 20))
    chair = box_instance("chair", slice(150, 199), slice(100, 140))
    depth = room_depth()
    depth[150:199, 100:140] = 3.0  # a chair-high box on the floor, 1 m in front of the wall
    cfg = PerceptionConfig()
    assert ("cabinet", 2.1) in cfg.max_top_m and "door" not in dict(cfg.max_top_m)
    assert drop_wall_pieces([strip, chair], depth, CAMERA, cfg, T_LEVEL, 0.0) == ([chair], 1)
    assert drop_wall_pieces([strip], depth, CAMERA, cfg, T_LEVEL, None) == ([strip], 0)
    off = PerceptionConfig(max_top_m=())
    assert drop_wall_pieces([strip], depth, CAMERA, off, T_LEVEL, 0.0) == ([strip], 0)
    with pytest.raises(ConfigError, match="max_top_m"):
        PerceptionConfig(max_top_m=(("cabinet", 0.0),))


def test_a_strip_of_floor_taken_for_a_cart_lies_flat_on_the_floor() -> None:
    """A 'cart' that is a strip of floor 2.5-2.7 m ahead is flagged, also under the nearer front
    of a bed's footboard; a cart standing there, a strip reaching the image's top rows, a strip
    without depth and the strip as an IV pole are not."""
    depth = corridor_depth(wall_m=4.0)
    rows, cols = slice(222, 230), slice(100, 160)  # floor rows 2.5-2.7 m ahead
    strip = box_instance("cart", rows, cols)
    tops = {"cart": 0.2}

    def flags(instances: list[Instance], d: np.ndarray, floor_z: float = 0.0, **kw: object) -> list[bool]:
        return flat_on_floor(instances, d, CAMERA, T_LEVEL, floor_z_m=floor_z, min_top_m=tops, **kw)

    assert flags([strip, box_instance("iv_pole", rows, cols)], depth) == [True, False]
    standing = depth.copy()
    standing[136:230, cols] = 2.5  # a 0.9 m cart at 2.5 m
    assert flags([box_instance("cart", slice(136, 230), cols)], standing) == [False]
    assert flags([box_instance("cart", slice(136, 230), cols)], standing, top_percentile=5.0) == [True]
    bed = depth.copy()
    bed[170:222, 90:170] = 2.3  # a footboard 0.2 m nearer, right above the strip
    assert flags([strip], bed) == [True]
    # The wall's top rows, 0-0.12 m above a floor put at 2.75 m: the mask may go on above the image.
    assert flags([box_instance("cart", slice(0, 9), cols)], depth, floor_z=2.75) == [False]
    assert flags([box_instance("cart", slice(4, 13), cols)], depth, floor_z=2.75) == [True]
    blind = depth.copy()
    blind[rows, cols] = 0.0
    assert flags([strip], blind) == [False]
    with pytest.raises(GeometryError):
        flags([strip], depth, top_percentile=0.0)
    with pytest.raises(GeometryError):
        flat_on_floor([strip], depth, CAMERA, np.eye(3), floor_z_m=0.0, min_top_m=tops)


def test_drop_floor_pieces_by_default_and_only_with_a_floor() -> None:
    strip = box_instance("cart", slice(222, 230), slice(100, 160))
    depth = corridor_depth(wall_m=4.0)
    cfg = PerceptionConfig()
    assert dict(cfg.min_top_m).get("cart") == 0.2 and "iv_pole" not in dict(cfg.min_top_m)
    assert drop_floor_pieces([strip], depth, CAMERA, cfg, T_LEVEL, 0.0) == ([], 1)
    assert drop_floor_pieces([strip], depth, CAMERA, cfg, T_LEVEL, None) == ([strip], 0)
    off = PerceptionConfig(min_top_m=())
    assert drop_floor_pieces([strip], depth, CAMERA, off, T_LEVEL, 0.0) == ([strip], 0)
    with pytest.raises(ConfigError, match="min_top_m"):
        PerceptionConfig(min_top_m=(("cart", 0.0),))


def test_drop_misplaced_runs_the_three_floor_checks_and_counts_each() -> None:
    """One call for the server, the offline runner and the bench: a floating "chair", a
    "cabinet" strip of wall and a "cart" strip on the floor are each left out by their own
    check and counted there; a standing chair stays; no floor keeps all four."""
    depth = room_depth()
    depth[150:199, 100:140] = 3.0  # a chair-high box on the floor, 1 m in front of the wall
    depth[106:152, 200:216] = 2.9  # a box hanging on the wall, clear of the floor
    depth[222:230, 250:300] = 3.5  # a strip along the floor
    chair = box_instance("chair", slice(150, 199), slice(100, 140))
    floating = box_instance("chair", slice(106, 152), slice(200, 216))
    strip = box_instance("cabinet", slice(130, 200), slice(0, 20))
    flat = box_instance("cart", slice(222, 230), slice(250, 300))
    given = [chair, floating, strip, flat]
    cfg = PerceptionConfig()
    assert drop_misplaced(given, depth, CAMERA, cfg, T_LEVEL, 0.0) == ([chair], LeftOut(1, 1, 1))
    assert drop_misplaced(given, depth, CAMERA, cfg, T_LEVEL, None) == (given, LeftOut(0, 0, 0))
