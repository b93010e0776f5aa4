"""The simulator's scenarios: a world, one or more robot paths, people, and lighting.

Scenario names are stable (tests, benchmarks and docs use them). ``aisle_*`` follow
paper 000 Table II (straight, left-turn and right-turn aisles, slow and at about twice
the speed); the rest exercise association traps, loop closure, dynamic people, darkness,
multi-robot mapping, and (``pan_in_place``) the fast turns that show a rolling shutter.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.errors import SimulationError
from wardmap.shared.se3 import yaw_transform
from wardmap.sim import furnish, models, textures
from wardmap.sim.actors import Actor, Carried, Pushed, Walker
from wardmap.sim.motion import Track, concat, hold, plan_path
from wardmap.sim.world import World, WorldBuilder

F64 = NDArray[np.float64]
SLOW_MPS = 0.4
QUICK_MPS = 0.8


@dataclass(frozen=True)
class RobotRun:
    """One robot's drive: its name (data-set folder) and base track in the world frame.

    ``world`` is this run's own world when it differs from the scene's (the same floor on
    another day, some objects moved: :meth:`World.with_objects_moved`); None: the scene's.
    """

    name: str
    track: Track
    world: World | None = None


@dataclass
class Scene:
    """A built scenario, ready to render."""

    name: str
    seed: int
    world: World
    robots: list[RobotRun]
    actors: list[Actor] = field(default_factory=list)
    light: Callable[[float], float] = lambda t: 1.0
    description: str = ""

    @property
    def duration(self) -> float:
        return max(r.track.t[-1] for r in self.robots)

    def world_of(self, run: RobotRun) -> World:
        """The world ``run`` drives in: its own, else the scene's."""
        return self.world if run.world is None else run.world


@dataclass(frozen=True)
class ScenarioSpec:
    name: str
    description: str
    build: Callable[[int], Scene]


# ---- worlds ---------------------------------------------------------------------------


def _aisle_world(name: str, seed: int, turn: int) -> tuple[World, list[list[float]]]:
    """A 3 m aisle, 15 m straight then (turn = +1 left, -1 right) 10 m; waypoints."""
    rng = np.random.default_rng(seed)
    b = WorldBuilder(name, rng)
    b.add_free(0, 0, 16, 3)
    if turn > 0:
        b.add_free(12.5, 0, 15.5, 14)
        b.add_free(4, 3, 9, 7, "ward")
        way = [[1.2, 1.5], [14.0, 1.5], [14.0, 11.5]]
    elif turn < 0:
        b.add_free(12.5, -11, 15.5, 3)
        b.add_free(4, -4, 9, 0, "ward")
        way = [[1.2, 1.5], [14.0, 1.5], [14.0, -8.5]]
    else:
        b.add_free(0, 0, 20, 3)
        b.add_free(6, 3, 11, 7, "ward")
        way = [[1.2, 1.5], [17.0, 1.5]]
    b.build_walls()
    furnish.furnish(b, rng, objects_per_m=0.25, fixtures_per_m=0.4)
    return b.finish(), way


def _loop_world(name: str, seed: int) -> WorldBuilder:
    """A ring corridor around a central block (centre line 64 m), a ward and a station."""
    rng = np.random.default_rng(seed)
    b = WorldBuilder(name, rng)
    b.add_free(0, 0, 24, 3)
    b.add_free(0, 11, 24, 14)
    b.add_free(0, 0, 3, 14)
    b.add_free(21, 0, 24, 14)
    b.add_free(9, 3, 15, 6, "station")
    b.add_free(5, 14, 12, 20, "ward")
    b.build_walls()
    return b


# ---- scenario builders ------------------------------------------------------------------


def _aisle(turn: int, speed: float, tag: str) -> Callable[[int], Scene]:
    def build(seed: int) -> Scene:
        world, way = _aisle_world(tag, seed, turn)
        track = plan_path(way, speed=speed, max_yaw_rate=0.5 * speed / SLOW_MPS, accel=0.3 * speed / SLOW_MPS)
        return Scene(tag, seed, world, [RobotRun("robot_0", track)])

    return build


def _ward_chairs(seed: int) -> Scene:
    rng = np.random.default_rng(seed)
    b = WorldBuilder("ward_chairs", rng)
    b.add_free(0, 0, 9, 7, "ward")
    b.add_free(-6, 2, 0, 5)
    b.build_walls()
    east, s_e = b.wall_near(9.0, 3.5)
    furnish.add_chair_row(b, east, s_e, 5, furnish.seat_texture(b, 0))
    north, s_n = b.wall_near(3.0, 7.0)
    furnish.add_chair_row(b, north, s_n, 3, furnish.seat_texture(b, 0))
    west, s_w = b.wall_near(0.0, 6.0)
    furnish.add_door_pair(b, west, s_w - 0.3, "W2")
    furnish.furnish(b, rng, trap=False, objects_per_m=0.3)
    track = plan_path(
        [[-4.5, 3.5], [7.0, 3.5], [7.0, 5.3], [2.0, 5.3], [2.0, 1.6], [7.5, 1.6]],
        speed=SLOW_MPS,
        turn_radius=0.6,
    )
    return Scene("ward_chairs", seed, b.finish(), [RobotRun("robot_0", track)])


def _hospital_loop(seed: int) -> Scene:
    b = _loop_world("hospital_loop", seed)
    furnish.furnish(b, b.rng)
    way = [[8.0, 1.5], [22.5, 1.5], [22.5, 12.5], [1.5, 12.5], [1.5, 1.5], [8.0, 1.5]]
    track = plan_path(way, speed=0.5, turn_radius=1.0)
    return Scene(
        "hospital_loop", seed, b.finish(), [RobotRun("robot_0", track)], description="closed circuit, 64 m"
    )


def _two_robots(seed: int) -> Scene:
    b = _loop_world("two_robots", seed)
    furnish.furnish(b, b.rng)
    a = plan_path([[4.0, 1.5], [22.5, 1.5], [22.5, 12.5], [13.0, 12.5]], speed=0.5, turn_radius=1.0)
    c = plan_path([[19.0, 12.5], [1.5, 12.5], [1.5, 1.5], [15.0, 1.5]], speed=0.5, turn_radius=1.0)
    return Scene(
        "two_robots",
        seed,
        b.finish(),
        [RobotRun("robot_0", a), RobotRun("robot_1", c)],
        description="two robots, paths overlap in the north and south corridors",
    )


def _two_robots_meet(seed: int) -> Scene:
    b = _loop_world("two_robots_meet", seed)
    furnish.furnish(b, b.rng)
    a = plan_path([[4.0, 1.5], [22.5, 1.5], [22.5, 12.5], [13.0, 12.5]], speed=0.5, turn_radius=1.0)
    c = plan_path([[1.5, 9.0], [1.5, 1.5], [15.0, 1.5]], speed=0.5, turn_radius=1.0)
    return Scene(
        "two_robots_meet",
        seed,
        b.finish(),
        [RobotRun("robot_0", a), RobotRun("robot_1", c)],
        description="two robots starting apart; after 15 s the second follows the first's path",
    )


DAY_S = 86_400.0
DAYS_MOVED = ("wheelchair", "cart", "chair")
"""Classes of the objects moved between the two days of ``hospital_days`` (one of each)."""


def _south_or_east(x: float, y: float) -> bool:
    """In the loop world's south or east corridor (the part both days of hospital_days drive)."""
    return y <= 3.0 or x >= 21.0


def _moves_between_days(b: WorldBuilder) -> dict[int, F64]:
    """One object of each :data:`DAYS_MOVED` class in the south or east corridor, and a new place
    for it on another wall there: ``id -> T_world_model``. An object of a class the furnishing did
    not put there is added first (it stands there on day 1)."""
    rng = b.rng
    walls = [
        k for k, w in enumerate(b.walls)
        if w.room == "corridor" and w.length >= 3.0 and _south_or_east(*(w.p0 + w.p1) / 2)
    ]
    width = {"wheelchair": 0.7, "cart": 0.85, "chair": 0.55}
    offset = {"wheelchair": 0.4, "cart": 0.3, "chair": 0.3}
    moves: dict[int, F64] = {}
    for cls in DAYS_MOVED:
        here = [
            o for o in b.objects
            if o.cls == cls and not o.note and _south_or_east(*o.T_world_model[:2, 3])
        ]
        if here:
            obj = here[int(rng.integers(len(here)))]
        else:
            parts = {
                "wheelchair": models.wheelchair,
                "cart": lambda: models.cart(
                    b.texture("cart_front", lambda g: textures.panelled(g, (200, 215, 230), 4, 1))
                ),
                "chair": lambda: models.chair(furnish.seat_texture(b, 1)),
            }[cls]()
            for k in rng.permutation(walls):
                s = b.free_interval(int(k), width[cls])
                if s is not None:
                    b.reserve(int(k), s, width[cls])
                    obj = b.add_object(cls, parts, b.on_wall(int(k), s, offset[cls]))
                    break
            else:
                raise SimulationError(f"hospital_days: no free wall for a {cls}")
        # Another wall if one has room, else at least 2 m along its own.
        own, s_own = b.wall_near(*obj.T_world_model[:2, 3])
        for k in [*(int(k) for k in rng.permutation(walls) if k != own), own, own, own]:
            s = b.free_interval(k, width[cls], margin=0.5, tries=100)
            if s is not None and (k != own or abs(s - s_own) >= 2.0):
                b.reserve(k, s, width[cls])
                moves[obj.id] = b.on_wall(k, s, offset[cls])
                break
        else:
            raise SimulationError(f"hospital_days: no free wall to move the {cls} to")
    return moves


def _hospital_days(seed: int) -> Scene:
    b = _loop_world("hospital_days", seed)
    furnish.furnish(b, b.rng)
    moves = _moves_between_days(b)
    day_1 = b.finish()
    day_2 = day_1.with_objects_moved(moves)
    # Day 1 starts in the south corridor and drives east, north, then west along the north
    # corridor; day 2, a day later, starts in the west corridor (never seen on day 1), drives
    # south, then east along the whole south corridor and north up the east one: 24 m of
    # day 1's path again in the same direction, seen again after the objects moved.
    a = plan_path([[4.0, 1.5], [22.5, 1.5], [22.5, 12.5], [10.0, 12.5]], speed=0.5, turn_radius=1.0)
    c = plan_path(
        [[1.5, 10.0], [1.5, 1.5], [22.5, 1.5], [22.5, 7.0]], speed=0.5, turn_radius=1.0, t0=DAY_S
    )
    return Scene(
        "hospital_days",
        seed,
        day_1,
        [RobotRun("day_1", a), RobotRun("day_2", c, world=day_2)],
        description="one robot on two days, started in different places; a wheelchair, a cart and "
        "a chair moved in between",
    )


def _people_textures(b: WorldBuilder) -> dict[str, str]:
    T = textures
    names = {
        "scrubs_blue": b.texture("scrubs_blue", lambda g: T.scrubs(g, (60, 110, 170))),
        "scrubs_green": b.texture("scrubs_green", lambda g: T.scrubs(g, (70, 150, 120))),
        "visitor": b.texture("visitor", lambda g: T.fabric(g, (150, 60, 60), pattern=True)),
        "gown": b.texture("gown", lambda g: T.fabric(g, (170, 200, 230), pattern=True)),
        "face_a": b.texture("face_a", lambda g: T.skin_face(g, (205, 165, 135))),
        "face_b": b.texture("face_b", lambda g: T.skin_face(g, (140, 100, 75))),
        "hair_a": b.texture("hair_a", lambda g: T.hair(g, (60, 40, 25))),
        "hair_b": b.texture("hair_b", lambda g: T.hair(g, (200, 180, 120))),
    }
    return names


def _walking_staff(seed: int) -> Scene:
    rng = np.random.default_rng(seed)
    b = WorldBuilder("walking_staff", rng)
    b.add_free(0, 0, 22, 3.2)
    b.add_free(8, 3.2, 12, 6, "station")
    b.build_walls()
    k_station, s_station = b.wall_near(10.0, 6.0)
    front = b.texture("desk_front", lambda g: textures.panelled(g, (180, 150, 110), 2, 4))
    desk = b.add_object("desk", models.desk(front), b.on_wall(k_station, s_station, 0.45))
    b.reserve(k_station, s_station, 2.6, both=True)
    furnish.furnish(b, rng, objects_per_m=0.2)
    tex = _people_textures(b)
    robot = plan_path([[1.0, 1.6], [13.0, 1.6]], speed=0.25)
    T_total = robot.t[-1]

    def walker(
        way: list[list[float]],
        t0: float,
        outfit: str,
        face: str,
        hair: str,
        role: str,
        speed: float = 1.1,
        accel: float = 1.0,
        **kw: object,
    ) -> Walker:
        tr = hold(
            plan_path(way, speed=speed, turn_radius=0.4, max_yaw_rate=2.0, accel=accel, t0=t0), T_total + 1
        )
        if tr.t[0] > 0:
            tr = Track(
                np.concatenate([[0.0], tr.t]),
                np.concatenate([[tr.x[0]], tr.x]),
                np.concatenate([[tr.y[0]], tr.y]),
                np.concatenate([[tr.yaw[0]], tr.yaw]),
                np.concatenate([[0.0], tr.s]),
            )
        return Walker(b.new_id(), tr, tex[outfit], tex[face], tex[hair], role, **kw)  # type: ignore[arg-type]

    # Staff walking towards the robot, passing on its left.
    p1 = walker([[20.0, 2.3], [2.0, 2.3]], 4.0, "scrubs_blue", "face_a", "hair_a", "staff")
    # A nurse pushing a cart ahead of the robot, in the same direction and at the robot's pace:
    # cart and nurse keep their place in the image, so their points look static to a tracker
    # that does not know what people are (the case dynamic-point removal exists for).
    p2 = walker(
        [[3.4, 1.45], [21.0, 1.45]],
        0.0,
        "scrubs_green",
        "face_b",
        "hair_b",
        "staff",
        speed=0.25,
        accel=0.4,
        arms_forward=True,
    )
    cart_front = b.texture("cart_front", lambda g: textures.panelled(g, (200, 215, 230), 4, 1))
    cart = Pushed(b.new_id(), "cart", models.cart(cart_front), p2)
    # A visitor crossing the corridor in front of the robot, twice.
    p3 = walker(
        [[9.0, 0.5], [9.5, 2.9], [7.0, 2.9], [6.5, 0.5]],
        8.0,
        "visitor",
        "face_b",
        "hair_a",
        "visitor",
        speed=0.9,
    )
    # A nurse carrying a temperature gun to the desk, setting it down, walking off.
    desk_xy = desk.T_world_model[:2, 3]
    stop = [float(desk_xy[0]) + 0.0, float(desk_xy[1]) - 1.0]
    leg1 = plan_path(
        [[16.0, 0.8], [stop[0] + 0.6, 1.6], stop],
        speed=1.0,
        turn_radius=0.4,
        max_yaw_rate=2.0,
        accel=1.0,
        t0=2.0,
    )
    leg2 = plan_path(
        [stop, [stop[0] + 0.3, 1.8], [20.0, 2.0]], speed=1.0, turn_radius=0.4, max_yaw_rate=2.0, accel=1.0
    )
    track4 = hold(concat(leg1, leg2, pause=3.0), T_total + 1)
    track4 = Track(
        np.concatenate([[0.0], track4.t]),
        np.concatenate([[track4.x[0]], track4.x]),
        np.concatenate([[track4.y[0]], track4.y]),
        np.concatenate([[track4.yaw[0]], track4.yaw]),
        np.concatenate([[0.0], track4.s]),
    )
    p4 = Walker(
        b.new_id(),
        track4,
        tex["scrubs_blue"],
        tex["face_a"],
        tex["hair_b"],
        "staff",
        height=1.65,
        arms_forward=True,
    )
    t_drop = float(leg1.t[-1]) + 1.0
    T_drop = desk.T_world_model @ yaw_transform(0.1, 0.3, 0.4, 0.78)
    gun = Carried(b.new_id(), "temperature_gun", models.temperature_gun(), p4, t_drop, T_drop)
    actors: list[Actor] = [p1, p2, cart, p3, p4, gun]
    return Scene(
        "walking_staff",
        seed,
        b.finish(),
        [RobotRun("robot_0", robot)],
        actors,
        description="four people: one passes, one pushes a cart, one crosses, "
        "one carries a temperature gun and sets it down on the desk",
    )


def _dark_corridor(seed: int) -> Scene:
    world, way = _aisle_world("dark_corridor", seed, +1)
    track = plan_path(way, speed=SLOW_MPS)
    t_off, t_on = 12.0, 24.0

    def light(t: float) -> float:
        # 1 s fades; 2 % of normal light while off (RGB near black, thermal unaffected).
        if t < t_off or t > t_on + 1.0:
            return 1.0
        if t < t_off + 1.0:
            return float(1.0 - 0.98 * (t - t_off))
        if t > t_on:
            return float(0.02 + 0.98 * (t - t_on))
        return 0.02

    return Scene(
        "dark_corridor",
        seed,
        world,
        [RobotRun("robot_0", track)],
        light=light,
        description=f"lights off from {t_off:.0f} s to {t_on:.0f} s",
    )


def _pan_in_place(seed: int) -> Scene:
    """Turning on the spot left and right in a furnished aisle, as one records a camera to
    calibrate its rolling shutter: yaw ``A sin(2 pi t / P)``, A = 40 deg, P = 4 s (up to
    1.1 rad/s), for 8 s after 0.5 s at rest."""
    world, _ = _aisle_world("pan_in_place", seed, 0)
    t = np.arange(0.0, 8.5 + 1e-9, 0.01)
    swing = np.where(t < 0.5, 0.0, np.radians(40.0) * np.sin(2.0 * np.pi * np.maximum(t - 0.5, 0.0) / 4.0))
    track = Track(t, np.full_like(t, 8.0), np.full_like(t, 1.5), swing, np.zeros_like(t))
    return Scene("pan_in_place", seed, world, [RobotRun("robot_0", track)],
                 description="turning on the spot, +-40 deg at up to 1.1 rad/s")


SCENARIOS: dict[str, ScenarioSpec] = {
    s.name: s
    for s in (
        ScenarioSpec("aisle_slow_1", "straight aisle, slow (0.4 m/s)", _aisle(0, SLOW_MPS, "aisle_slow_1")),
        ScenarioSpec("aisle_slow_2", "left-turn aisle, slow", _aisle(+1, SLOW_MPS, "aisle_slow_2")),
        ScenarioSpec("aisle_slow_3", "right-turn aisle, slow", _aisle(-1, SLOW_MPS, "aisle_slow_3")),
        ScenarioSpec(
            "aisle_quick_1", "straight aisle, quick (0.8 m/s)", _aisle(0, QUICK_MPS, "aisle_quick_1")
        ),
        ScenarioSpec("aisle_quick_2", "left-turn aisle, quick", _aisle(+1, QUICK_MPS, "aisle_quick_2")),
        ScenarioSpec("aisle_quick_3", "right-turn aisle, quick", _aisle(-1, QUICK_MPS, "aisle_quick_3")),
        ScenarioSpec(
            "ward_chairs", "a ward with rows of identical chairs and a pair of identical doors", _ward_chairs
        ),
        ScenarioSpec("hospital_loop", "a 64 m closed corridor circuit back to the start", _hospital_loop),
        ScenarioSpec(
            "walking_staff",
            "people walking, pushing a cart, carrying and setting down an item",
            _walking_staff,
        ),
        ScenarioSpec("dark_corridor", "the lights go out for 12 s (thermal keeps working)", _dark_corridor),
        ScenarioSpec("pan_in_place", "turning on the spot left and right (+-40 deg): for a rolling "
                     "shutter's calibration", _pan_in_place),
        ScenarioSpec("two_robots", "two robots in one world with overlapping paths", _two_robots),
        ScenarioSpec(
            "two_robots_meet",
            "two robots starting apart in one world; the second joins the first's path (anchoring)",
            _two_robots_meet,
        ),
        ScenarioSpec(
            "hospital_days",
            "one robot on two days from different starts, some objects moved in between",
            _hospital_days,
        ),
    )
}


def build_scene(name: str, seed: int) -> Scene:
    """Build scenario ``name`` with ``seed``; :class:`SimulationError` lists known names."""
    spec = SCENARIOS.get(name)
    if spec is None:
        raise SimulationError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
    if seed < 0:
        raise SimulationError(f"seed must be >= 0, got {seed}")
    scene = spec.build(seed)
    if not scene.description:
        scene.description = spec.description
    return scene
