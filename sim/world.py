"""Procedural hospital floors: free space, walls, fixtures and knowledge-graph objects.

A floor is the union of axis-aligned free rectangles (corridors, wards, the nurse
station). Walls follow the boundary of that union; objects stand against walls facing
into the room or at given places. Everything static is merged into one
:class:`~wardmap.sim.geometry.TriangleSoup`; each object of a knowledge-graph class keeps
an instance id, a class, ``T_world_object`` (its bounding-box centre, x forward, z up)
and a size for ``objects.json``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.errors import SimulationError
from wardmap.shared.se3 import yaw_transform
from wardmap.sim import textures
from wardmap.sim.geometry import Part, TriangleSoup, box_soup, part_transform, parts_bounds, quad_soup
from wardmap.sim.materials import material_id

F64 = NDArray[np.float64]

WALL_HEIGHT_M = 2.7
GRID_M = 0.1
WALL_TEXELS_PER_M = 128.0
FLOOR_TEXELS_PER_M = 213.0


@dataclass(frozen=True)
class Rect:
    """Free floor space ``[x0, x1] x [y0, y1]`` in metres (world frame); ``kind`` names it."""

    x0: float
    y0: float
    x1: float
    y1: float
    kind: str = "corridor"


@dataclass(frozen=True)
class WallSegment:
    """A straight wall from ``p0`` to ``p1`` (2,) with ``normal`` (2,) pointing into free space."""

    p0: F64
    p1: F64
    normal: F64
    room: str

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.p1 - self.p0))

    @property
    def direction(self) -> F64:
        return (self.p1 - self.p0) / self.length

    def point(self, s: float, offset: float = 0.0) -> F64:
        """Point (2,) at arc length ``s`` along the wall, ``offset`` metres into the room."""
        return self.p0 + self.direction * s + self.normal * offset


@dataclass
class PlacedObject:
    """An object instance of a knowledge-graph class in the world.

    ``T_world_model`` places the model frame (origin on the floor); ``T_world_object`` is
    the bounding-box centre with the model's axes; ``size`` the box edges in metres.
    """

    id: int
    cls: str
    parts: tuple[Part, ...]
    T_world_model: F64
    T_world_object: F64
    size: F64
    note: str = ""


def object_pose(parts: tuple[Part, ...], T_world_model: F64) -> tuple[F64, F64]:
    """``(T_world_object, size)`` of a model placed at ``T_world_model``."""
    lo, hi = parts_bounds(parts)
    T = np.eye(4)
    T[:3, 3] = (lo + hi) / 2.0
    return T_world_model @ T, hi - lo


def soup_of(
    parts: tuple[Part, ...], T_world_model: F64, instance: int, bank: textures.TextureBank
) -> TriangleSoup:
    """Triangles of a model's parts placed at ``T_world_model``, tagged with ``instance``."""
    return TriangleSoup.concat(
        [
            box_soup(
                part_transform(T_world_model, p),
                p.size,
                bank.id(p.texture),
                material_id(p.material),
                instance,
                p.texels_per_m,
            )
            for p in parts
        ]
    )


@dataclass
class World:
    """A finished world: textures, static triangles, objects, free space and walls."""

    name: str
    bank: textures.TextureBank
    static: TriangleSoup
    objects: list[PlacedObject]
    free: list[Rect]
    walls: list[WallSegment]
    next_id: int

    def with_objects_moved(self, moves: Mapping[int, F64], note: str = "moved") -> World:
        """A copy of this world with objects placed anew (e.g. a robot's next day).

        Args:
            moves: object id -> its new ``T_world_model`` (4, 4). Only objects whose triangles
                all carry their own instance id can move (no decor of instance 0 attached).
            note: the moved objects' new ``note`` (``objects.json``).

        Raises:
            SimulationError: an id that is no object of this world.
        """
        known = {o.id for o in self.objects}
        unknown = sorted(set(moves) - known)
        if unknown:
            raise SimulationError(f"cannot move objects {unknown}: no such object in world {self.name!r}")
        keep = ~np.isin(self.static.instance, np.fromiter(moves, np.int64, len(moves)))
        soups = [self.static.select(keep)]
        objects = []
        for o in self.objects:
            if o.id in moves:
                T_world_model = np.asarray(moves[o.id], np.float64)
                T_obj, size = object_pose(o.parts, T_world_model)
                o = PlacedObject(o.id, o.cls, o.parts, T_world_model, T_obj, size, note)
                soups.append(soup_of(o.parts, T_world_model, o.id, self.bank))
            objects.append(o)
        return World(self.name, self.bank, TriangleSoup.concat(soups), objects, list(self.free),
                     list(self.walls), self.next_id)


class WorldBuilder:
    """Builds a :class:`World` step by step; deterministic for a given generator."""

    def __init__(self, name: str, rng: np.random.Generator) -> None:
        self.name = name
        self.rng = rng
        self.bank = textures.TextureBank()
        self.free: list[Rect] = []
        self.walls: list[WallSegment] = []
        self._soups: list[TriangleSoup] = []
        self.objects: list[PlacedObject] = []
        self._next_id = 1
        self._busy: dict[int, list[tuple[float, float]]] = {}
        self._busy_high: dict[int, list[tuple[float, float]]] = {}
        self._base_textures()

    # ---- textures -------------------------------------------------------------------
    def texture(self, name: str, factory: Callable[[np.random.Generator], textures.U8]) -> str:
        """Create texture ``name`` once with ``factory(rng)``; returns the name."""
        if name not in self.bank:
            self.bank.add(name, factory(self.rng))
        return name

    def _base_textures(self) -> None:
        T = textures
        solid = lambda col: lambda g: T.fabric(g, col)  # noqa: E731
        self.texture("floor", lambda g: T.speckled(g, (196, 190, 178), grid=2))
        self.texture("floor_ward", lambda g: T.speckled(g, (170, 190, 200), grid=2, grout=(120, 135, 140)))
        self.texture("ceiling", T.ceiling_tiles)
        self.texture("light", lambda g: T.speckled(g, (252, 252, 246), speckle=20, amp=2.0))
        for k, col in enumerate(((224, 228, 214), (212, 222, 232), (236, 226, 206))):
            self.texture(f"wall_{k}", functools.partial(T.painted_wall, color=col))
        self.texture("skirting", lambda g: T.metal(g, (90, 96, 104)))
        self.texture("chrome", T.metal)
        self.texture("black", solid((35, 35, 38)))
        self.texture("bed_frame", lambda g: T.metal(g, (210, 212, 215)))
        self.texture("bed_board", lambda g: T.panelled(g, (225, 215, 190), 1, 2))
        self.texture("pillow", solid((240, 240, 236)))
        self.texture("wheelchair_seat", lambda g: T.fabric(g, (40, 60, 110), pattern=True))
        self.texture("wheel", lambda g: T.metal(g, (60, 60, 64)))
        self.texture("tray", lambda g: T.metal(g, (200, 205, 210)))
        self.texture("iv_bag", lambda g: T.speckled(g, (230, 236, 240), speckle=60))
        self.texture("gun", lambda g: T.panelled(g, (240, 240, 245), 1, 1))
        self.texture("cup", lambda g: T.fabric(g, (250, 250, 250), pattern=True))
        self.texture("ceramic", lambda g: T.speckled(g, (238, 238, 240), speckle=40, amp=3.0))
        self.texture("desk_top", lambda g: T.speckled(g, (190, 170, 140), speckle=300))
        self.texture("door_frame", lambda g: T.metal(g, (150, 155, 160)))
        self.texture("rail", lambda g: T.metal(g, (180, 150, 110)))
        self.texture("board", lambda g: T.speckled(g, (170, 120, 80), speckle=500))
        self.texture("extinguisher", lambda g: T.sign(g, "FIRE", (200, 20, 20), (255, 255, 255)))
        self.texture("radiator", lambda g: T.panelled(g, (235, 235, 235), 1, 8))
        self.texture("mirror", lambda g: T.metal(g, (180, 190, 200)))

    # ---- layout ---------------------------------------------------------------------
    def add_free(self, x0: float, y0: float, x1: float, y1: float, kind: str = "corridor") -> None:
        self.free.append(Rect(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1), kind))

    def room_at(self, x: float, y: float) -> str:
        for r in reversed(self.free):
            if r.x0 <= x <= r.x1 and r.y0 <= y <= r.y1:
                return r.kind
        return "corridor"

    def build_walls(self) -> None:
        """Extract wall segments from the boundary of the free-space union (0.1 m grid)."""
        xs = [v for r in self.free for v in (r.x0, r.x1)]
        ys = [v for r in self.free for v in (r.y0, r.y1)]
        ox, oy = min(xs) - 1.0, min(ys) - 1.0
        nx = round((max(xs) + 1.0 - ox) / GRID_M)
        ny = round((max(ys) + 1.0 - oy) / GRID_M)
        occ = np.zeros((nx, ny), bool)
        for r in self.free:
            i0, i1 = round((r.x0 - ox) / GRID_M), round((r.x1 - ox) / GRID_M)
            j0, j1 = round((r.y0 - oy) / GRID_M), round((r.y1 - oy) / GRID_M)
            occ[i0:i1, j0:j1] = True
        segs: list[WallSegment] = []
        # Vertical walls at x = ox + i*GRID between cells i-1 and i.
        diff_x = occ[1:, :].astype(np.int8) - occ[:-1, :].astype(np.int8)
        for i in range(diff_x.shape[0]):
            for sign in (1, -1):
                col = diff_x[i] == sign
                for j0, j1 in _runs(col):
                    x = ox + (i + 1) * GRID_M
                    p0 = np.array([x, oy + j0 * GRID_M])
                    p1 = np.array([x, oy + j1 * GRID_M])
                    normal = np.array([float(sign), 0.0])  # free side is +x when sign = 1
                    segs.append(self._segment(p0, p1, normal))
        diff_y = occ[:, 1:].astype(np.int8) - occ[:, :-1].astype(np.int8)
        for j in range(diff_y.shape[1]):
            for sign in (1, -1):
                row = diff_y[:, j] == sign
                for i0, i1 in _runs(row):
                    y = oy + (j + 1) * GRID_M
                    p0 = np.array([ox + i0 * GRID_M, y])
                    p1 = np.array([ox + i1 * GRID_M, y])
                    segs.append(self._segment(p0, p1, np.array([0.0, float(sign)])))
        self.walls = segs
        for k in range(len(segs)):
            self._busy[k] = []
            self._busy_high[k] = []
        self._surfaces()

    def _segment(self, p0: F64, p1: F64, normal: F64) -> WallSegment:
        # Orient so that the normal is to the left of p0 -> p1 (texture reads left to right).
        d = p1 - p0
        if d[0] * normal[1] - d[1] * normal[0] < 0:
            p0, p1 = p1, p0
        mid = (p0 + p1) / 2 + normal * 0.2
        return WallSegment(p0, p1, normal, self.room_at(float(mid[0]), float(mid[1])))

    def _surfaces(self) -> None:
        """Floor, ceiling, lights, walls and skirting boards."""
        up, down = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])
        fl, fw, ce = self.bank.id("floor"), self.bank.id("floor_ward"), self.bank.id("ceiling")
        light_tex = self.bank.id("light")
        for r in self.free:
            c = np.array([[r.x0, r.y0, 0], [r.x1, r.y0, 0], [r.x1, r.y1, 0], [r.x0, r.y1, 0]], float)
            uv = c[:, :2] * FLOOR_TEXELS_PER_M
            tex = fw if r.kind == "ward" else fl
            self._soups.append(quad_soup(c, uv, tex, material_id("floor"), 0, up))
            cc = c.copy()
            cc[:, 2] = WALL_HEIGHT_M
            self._soups.append(
                quad_soup(cc, cc[:, :2] * FLOOR_TEXELS_PER_M, ce, material_id("ceiling"), 0, down)
            )
            # Ceiling light panels on a 2.4 m grid inside the rectangle.
            for x in np.arange(r.x0 + 1.2, r.x1 - 0.5, 2.4):
                for y in np.arange(r.y0 + 1.2, r.y1 - 0.5, 2.4):
                    lc = np.array(
                        [[x - 0.3, y - 0.3], [x + 0.3, y - 0.3], [x + 0.3, y + 0.3], [x - 0.3, y + 0.3]]
                    )
                    q = np.column_stack([lc, np.full(4, WALL_HEIGHT_M - 0.01)])
                    uv_l = np.array([[0, 0], [255, 0], [255, 255], [0, 255]], float)
                    self._soups.append(quad_soup(q, uv_l, light_tex, material_id("ceiling_light"), 0, down))
        for k, w in enumerate(self.walls):
            tex = self.bank.id(f"wall_{int(self.rng.integers(0, 3))}")
            c = np.array([[*w.p0, 0.0], [*w.p1, 0.0], [*w.p1, WALL_HEIGHT_M], [*w.p0, WALL_HEIGHT_M]])
            u0 = float(self.rng.uniform(0, 256))
            uv = np.array([[u0, WALL_HEIGHT_M], [u0 + w.length, WALL_HEIGHT_M], [u0 + w.length, 0], [u0, 0]])
            uv[:, 0] = u0 + (uv[:, 0] - u0) * WALL_TEXELS_PER_M
            uv[:, 1] *= WALL_TEXELS_PER_M
            self._soups.append(quad_soup(c, uv, tex, material_id("wall"), 0, np.array([*w.normal, 0.0])))
            self._wall_box(k, 0.0, w.length, 0.008, 0.05, 0.1, "skirting", "plastic")

    def _wall_box(
        self,
        k: int,
        s0: float,
        s1: float,
        depth: float,
        z: float,
        h: float,
        tex: str,
        mat: str,
        instance: int = 0,
    ) -> None:
        """A flat box on wall ``k`` from arc length s0 to s1, centred at height z."""
        w = self.walls[k]
        mid = w.point((s0 + s1) / 2, depth / 2 + 0.002)
        yaw = float(np.arctan2(w.normal[1], w.normal[0]))
        T = yaw_transform(float(mid[0]), float(mid[1]), yaw, z)
        self._soups.append(
            box_soup(
                T,
                (depth, s1 - s0, h),
                self.bank.id(tex),
                material_id(mat),
                instance,
                200.0 if tex in ("skirting", "rail") else 0.0,
            )
        )

    # ---- placement ------------------------------------------------------------------
    def free_interval(
        self, k: int, width: float, *, high: bool = False, margin: float = 1.0, tries: int = 20
    ) -> float | None:
        """A random arc length on wall ``k`` with ``width`` metres free; None if full."""
        w = self.walls[k]
        busy = self._busy_high[k] if high else self._busy[k]
        lo, hi = margin + width / 2, w.length - margin - width / 2
        if hi < lo:
            return None
        for _ in range(tries):
            s = float(self.rng.uniform(lo, hi))
            if all(s + width / 2 + 0.15 < a or s - width / 2 - 0.15 > b for a, b in busy):
                return s
        return None

    def reserve(self, k: int, s: float, width: float, *, high: bool = False, both: bool = False) -> None:
        span = (s - width / 2, s + width / 2)
        if both or not high:
            self._busy[k].append(span)
        if both or high:
            self._busy_high[k].append(span)

    def new_id(self) -> int:
        i = self._next_id
        self._next_id += 1
        return i

    def add_object(
        self, cls: str, parts: tuple[Part, ...], T_world_model: F64, note: str = ""
    ) -> PlacedObject:
        """Place a knowledge-graph object; it gets the next instance id."""
        oid = self.new_id()
        T_obj, size = object_pose(parts, T_world_model)
        obj = PlacedObject(oid, cls, parts, T_world_model, T_obj, size, note)
        self.objects.append(obj)
        self._soups.append(soup_of(parts, T_world_model, oid, self.bank))
        return obj

    def add_decor(self, parts: tuple[Part, ...], T_world_model: F64) -> None:
        """Static scenery that is no knowledge-graph object (instance 0)."""
        self._soups.append(soup_of(parts, T_world_model, 0, self.bank))

    def on_wall(self, k: int, s: float, offset: float = 0.0) -> F64:
        """``T_world_model`` facing out of wall ``k`` at arc length ``s``."""
        w = self.walls[k]
        p = w.point(s, offset)
        return yaw_transform(float(p[0]), float(p[1]), float(np.arctan2(w.normal[1], w.normal[0])))

    def wall_near(self, x: float, y: float) -> tuple[int, float]:
        """Index and arc length of the wall segment closest to (x, y)."""
        best, best_d, best_s = -1, np.inf, 0.0
        q = np.array([x, y])
        for k, w in enumerate(self.walls):
            s = float(np.clip((q - w.p0) @ w.direction, 0.0, w.length))
            d = float(np.linalg.norm(w.point(s) - q))
            if d < best_d:
                best, best_d, best_s = k, d, s
        return best, best_s

    def finish(self) -> World:
        return World(
            self.name,
            self.bank,
            TriangleSoup.concat(self._soups),
            self.objects,
            self.free,
            self.walls,
            self._next_id,
        )


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """Half-open index runs ``[a, b)`` where ``mask`` is True."""
    if not mask.any():
        return []
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), ends.tolist(), strict=True))
