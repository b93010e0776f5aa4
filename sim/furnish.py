"""Furnishing a hospital floor: doors, fixtures on the walls, and objects by room kind.

Every world gets the association trap of paper 000 Fig. 1: a pair of identical doors
side by side and a row of identical chairs.
"""

from __future__ import annotations

import numpy as np

from wardmap.sim import models, textures
from wardmap.sim.geometry import Part
from wardmap.sim.world import WorldBuilder

_DOOR_COLOURS = ((170, 120, 70), (120, 150, 190), (150, 170, 120), (200, 190, 160))
_SEAT_COLOURS = ((160, 40, 40), (40, 110, 160), (60, 130, 80), (180, 140, 40))


def door_texture(b: WorldBuilder, number: str, colour_index: int) -> str:
    col = _DOOR_COLOURS[colour_index % len(_DOOR_COLOURS)]
    return b.texture(f"door_{number}", lambda g: textures.door(g, col, number))


def add_door(b: WorldBuilder, k: int, s: float, leaf: str, note: str = "") -> None:
    b.add_object("door", models.door(leaf), b.on_wall(k, s), note)
    b.reserve(k, s, 1.25, both=True)


def add_door_pair(b: WorldBuilder, k: int, s: float, number: str) -> None:
    """Two identical doors side by side (same leaf texture): the association trap."""
    leaf = door_texture(b, number, 1)
    for ds in (-0.62, 0.62):
        b.add_object("door", models.door(leaf), b.on_wall(k, s + ds), "identical_pair")
    b.reserve(k, s, 2.5, both=True)


def add_chair_row(b: WorldBuilder, k: int, s: float, n: int, seat: str, spacing: float = 0.55) -> None:
    """``n`` identical chairs in a row against wall ``k``, centred at arc length ``s``."""
    for i in range(n):
        si = s + (i - (n - 1) / 2) * spacing
        b.add_object("chair", models.chair(seat), b.on_wall(k, si, 0.3), "identical_row")
    b.reserve(k, s, n * spacing + 0.1)


def seat_texture(b: WorldBuilder, index: int) -> str:
    col = _SEAT_COLOURS[index % len(_SEAT_COLOURS)]
    return b.texture(f"seat_{index}", lambda g: textures.fabric(g, col, pattern=True))


def _high_fixtures(b: WorldBuilder, k: int, rng: np.random.Generator, per_m: float) -> None:
    """Posters, signs, notice boards and extinguishers at eye height on wall ``k``."""
    w = b.walls[k]
    n = round(w.length * per_m)
    for _ in range(n):
        parts: tuple[Part, ...]
        kind = rng.choice(["poster", "poster", "sign", "board", "extinguisher", "clock"])
        width = {"poster": 0.6, "sign": 0.55, "board": 1.0, "extinguisher": 0.3, "clock": 0.3}[str(kind)]
        s = b.free_interval(k, width, high=True, margin=0.4)
        if s is None:
            continue
        b.reserve(k, s, width, high=True)
        if kind == "poster":
            name = b.texture(f"poster_{len(b.bank)}", textures.poster)
            parts = (Part((0.005, 0, 1.55), (0.01, 0.6, 0.8), name, "poster"),)
        elif kind == "sign":
            word = str(rng.choice(["WARD 3\nEAST", "EXIT", "ICU", "X-RAY", "LAB", "PHARMACY", "LIFT"]))
            bgs = ((20, 60, 140), (20, 110, 60), (150, 30, 30))
            bg = bgs[int(rng.integers(0, len(bgs)))]

            def make_sign(g: np.random.Generator, t: str = word, c: tuple[int, int, int] = bg) -> textures.U8:
                return textures.sign(g, t, c, (255, 255, 255))

            name = b.texture(f"sign_{len(b.bank)}", make_sign)
            parts = (Part((0.01, 0, 2.05), (0.02, 0.55, 0.4), name, "sign"),)
        elif kind == "board":
            name = b.texture(f"poster_{len(b.bank)}", textures.poster)
            parts = (
                Part((0.01, 0, 1.5), (0.02, 1.0, 0.7), "board", "wood", 300.0),
                Part((0.025, -0.2, 1.55), (0.01, 0.4, 0.45), name, "poster"),
            )
        elif kind == "extinguisher":
            parts = (Part((0.08, 0, 0.9), (0.16, 0.16, 0.5), "extinguisher", "plastic"),)
            b.reserve(k, s, width)
        else:
            name = b.texture(f"clock_{len(b.bank)}", textures.poster)
            parts = (Part((0.02, 0, 2.1), (0.04, 0.3, 0.3), name, "plastic"),)
        b.add_decor(parts, b.on_wall(k, s))


def _rails(b: WorldBuilder, k: int) -> None:
    """Handrails at 0.9 m along corridor walls, interrupted by doors and objects."""
    w = b.walls[k]
    busy = sorted(b._busy[k])
    s = 0.15
    for a, e in [*busy, (w.length - 0.15, w.length)]:
        if a - s > 0.6:
            b._wall_box(k, s, a, 0.06, 0.9, 0.05, "rail", "wood")
        s = max(s, e)


def furnish(
    b: WorldBuilder,
    rng: np.random.Generator,
    *,
    door_every_m: float = 6.0,
    fixtures_per_m: float = 0.35,
    objects_per_m: float = 0.2,
    trap: bool = True,
    skip_walls: tuple[int, ...] = (),
) -> None:
    """Populate every wall: doors, the trap pair, objects by room kind, fixtures, rails."""
    order = sorted(range(len(b.walls)), key=lambda i: -b.walls[i].length)
    walls = [k for k in order if k not in skip_walls]
    if trap and walls:
        k = walls[0]
        s = b.free_interval(k, 2.6)
        if s is not None:
            add_door_pair(b, k, s, f"{int(rng.integers(100, 400))}")
    door_no = int(rng.integers(1, 40))
    for k in walls:
        w = b.walls[k]
        for _ in range(int(w.length // door_every_m)):
            s = b.free_interval(k, 1.3)
            if s is None:
                break
            door_no += 1
            add_door(b, k, s, door_texture(b, str(door_no), door_no))
    if trap and len(walls) > 1:
        k = walls[1]
        s = b.free_interval(k, 4 * 0.55 + 0.2)
        if s is not None:
            add_chair_row(b, k, s, 4, seat_texture(b, 0))
    for k in walls:
        w = b.walls[k]
        for _ in range(round(w.length * objects_per_m)):
            _object_for_room(b, k, rng, w.room)
        _high_fixtures(b, k, rng, fixtures_per_m)
        if w.room == "corridor":
            _rails(b, k)


def _object_for_room(b: WorldBuilder, k: int, rng: np.random.Generator, room: str) -> None:
    if room == "ward":
        choices = ["bed", "bed", "iv_pole", "cabinet", "sink", "wall_monitor", "chair", "wheelchair"]
    elif room == "station":
        choices = ["desk", "cabinet", "wall_monitor", "cart", "chair"]
    else:
        choices = ["bed", "wheelchair", "cart", "iv_pole", "cabinet", "wall_monitor", "chair", "sink"]
    cls = str(rng.choice(choices))
    width = {
        "bed": 2.1,
        "wheelchair": 0.7,
        "cart": 0.85,
        "iv_pole": 0.55,
        "cabinet": 1.05,
        "wall_monitor": 0.75,
        "chair": 0.55,
        "sink": 0.65,
        "desk": 2.5,
    }[cls]
    high = cls == "wall_monitor"
    s = b.free_interval(k, width, high=high)
    if s is None:
        return
    b.reserve(k, s, width, both=cls in ("cabinet", "wall_monitor", "desk"), high=high)
    if cls == "bed":
        sheet = b.texture(
            f"sheet_{int(rng.integers(0, 3))}",
            lambda g: textures.fabric(
                g, (int(g.integers(150, 240)), int(g.integers(180, 240)), 240), pattern=True
            ),
        )
        b.add_object("bed", models.bed(sheet), b.on_wall(k, s, 0.5))
    elif cls == "wheelchair":
        b.add_object("wheelchair", models.wheelchair(), b.on_wall(k, s, 0.4))
    elif cls == "cart":
        front = b.texture("cart_front", lambda g: textures.panelled(g, (200, 215, 230), 4, 1))
        b.add_object("cart", models.cart(front), b.on_wall(k, s, 0.3))
    elif cls == "iv_pole":
        b.add_object("iv_pole", models.iv_pole(), b.on_wall(k, s, 0.3))
    elif cls == "cabinet":
        front = b.texture(
            f"cabinet_{int(rng.integers(0, 2))}",
            lambda g: textures.panelled(g, (int(g.integers(190, 240)), 210, 200), 3, 2),
        )
        b.add_object("cabinet", models.cabinet(front), b.on_wall(k, s, 0.26))
    elif cls == "wall_monitor":
        scr = b.texture(f"screen_{len(b.bank)}", textures.screen)
        b.add_object("wall_monitor", models.wall_monitor(scr), b.on_wall(k, s, 0.03))
    elif cls == "chair":
        b.add_object("chair", models.chair(seat_texture(b, int(rng.integers(1, 4)))), b.on_wall(k, s, 0.3))
    elif cls == "sink":
        b.add_object("sink", models.sink(), b.on_wall(k, s, 0.25))
        b.add_decor((Part((0.01, 0, 1.45), (0.02, 0.5, 0.6), "mirror", "glass"),), b.on_wall(k, s))
        b.reserve(k, s, width, high=True)
    elif cls == "desk":
        front = b.texture("desk_front", lambda g: textures.panelled(g, (180, 150, 110), 2, 4))
        b.add_object("desk", models.desk(front), b.on_wall(k, s, 0.45))
