"""Scenario content: every scenario builds, carries the association trap, and the
special scenarios do what their names promise."""

from __future__ import annotations

import numpy as np
import pytest

from wardmap.shared.errors import SimulationError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.sim.scenarios import SCENARIOS, build_scene


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_every_scenario_builds_with_known_classes_and_a_trap(name: str) -> None:
    """Each scenario's world uses only knowledge-graph classes and has near-identical
    objects side by side (identical door pair or identical chair row, paper 000 Fig. 1)."""
    kg = KnowledgeGraph.load()
    scene = build_scene(name, 3)
    classes = {o.cls for o in scene.world.objects} | {a.cls for a in scene.actors}
    assert classes <= set(kg.names)
    notes = [o.note for o in scene.world.objects]
    assert notes.count("identical_pair") == 2 or notes.count("identical_row") >= 3
    for run in scene.robots:
        assert run.track.duration > 5.0
        assert np.all(np.diff(run.track.t) > 0)


def test_unknown_scenario_lists_the_known_ones() -> None:
    """A typo in the scenario name raises SimulationError naming the choices."""
    with pytest.raises(SimulationError, match="aisle_slow_1"):
        build_scene("aisle_slwo_1", 0)


def test_quick_aisles_are_about_twice_as_fast() -> None:
    """aisle_quick_k drives the same path as aisle_slow_k in about half the time."""
    for k in (1, 2, 3):
        slow = build_scene(f"aisle_slow_{k}", 0).robots[0].track
        quick = build_scene(f"aisle_quick_{k}", 0).robots[0].track
        assert quick.length == pytest.approx(slow.length, rel=1e-6)
        assert 1.6 < slow.duration / quick.duration < 2.2


def test_hospital_loop_is_a_closed_circuit_of_60m() -> None:
    """The loop is at least 60 m long and ends where it started, heading the same way."""
    track = build_scene("hospital_loop", 0).robots[0].track
    assert track.length >= 60.0
    assert np.hypot(track.x[-1] - track.x[0], track.y[-1] - track.y[0]) < 0.05
    dyaw = (track.yaw[-1] - track.yaw[0] + np.pi) % (2 * np.pi) - np.pi
    assert abs(dyaw) < np.radians(2.0)


def test_ward_chairs_has_a_row_of_identical_chairs() -> None:
    """At least four chairs with the same model stand within 0.6 m of their neighbours."""
    scene = build_scene("ward_chairs", 0)
    chairs = [o for o in scene.world.objects if o.cls == "chair" and o.note == "identical_row"]
    assert len(chairs) >= 4
    xy = np.array([o.T_world_object[:2, 3] for o in chairs])
    nearest = np.sort(np.linalg.norm(xy[:, None] - xy[None], axis=2), axis=1)[:, 1]
    assert np.all(nearest < 0.6)
    assert len({o.parts for o in chairs}) <= 2  # same model (two rows may share it)


def test_walking_staff_people_cart_and_carried_item() -> None:
    """Three or more people walk; a cart moves with its pusher; the temperature gun
    moves while carried and stays put after it is set down."""
    scene = build_scene("walking_staff", 0)
    people = [a for a in scene.actors if a.cls == "person"]
    assert len(people) >= 3
    ts = np.linspace(0.0, scene.duration, 60)
    for p in people:
        xy = np.array([p.object_pose(float(t))[0][:2, 3] for t in ts])
        assert np.ptp(xy, axis=0).max() > 2.0, "every person walks"
    cart = next(a for a in scene.actors if a.cls == "cart")
    cxy = np.array([cart.object_pose(float(t))[0][:2, 3] for t in ts])
    assert np.ptp(cxy, axis=0).max() > 2.0
    gun = next(a for a in scene.actors if a.cls == "temperature_gun")
    t_drop = gun.t_drop  # type: ignore[union-attr]
    before = [gun.object_pose(t)[0][:3, 3] for t in (1.0, t_drop - 1.0)]
    after = [gun.object_pose(t)[0][:3, 3] for t in (t_drop + 2.0, scene.duration)]
    assert np.linalg.norm(before[1] - before[0]) > 0.5
    assert np.allclose(after[0], after[1])
    assert after[0][2] > 0.7, "set down on the desk top"


def test_dark_corridor_switches_the_lights_off() -> None:
    """Light is normal at the start, near zero in the middle, and back at the end."""
    scene = build_scene("dark_corridor", 0)
    assert scene.light(1.0) == 1.0
    assert scene.light(18.0) < 0.05
    assert scene.light(scene.duration) == 1.0


def test_two_robots_share_a_world_and_overlap() -> None:
    """Two robots whose paths come within 0.5 m of each other over several metres."""
    scene = build_scene("two_robots", 0)
    assert len(scene.robots) == 2
    a, b = scene.robots
    pa = np.column_stack([a.track.x, a.track.y])[::20]
    pb = np.column_stack([b.track.x, b.track.y])[::20]
    d = np.linalg.norm(pa[:, None] - pb[None], axis=2).min(axis=1)
    assert (d < 0.5).sum() * 20 * 0.01 > 5.0  # metres of a's path near b's


def _looking_at(T_world_model: np.ndarray, distance: float = 2.5) -> np.ndarray:
    """A camera ``distance`` metres in front of a wall object (along its model x axis), 1 m above
    the floor, looking back at it (camera x right, y down, z forward)."""
    x_model = T_world_model[:3, 0] / np.linalg.norm(T_world_model[:3, 0])
    z_cam = -np.array([x_model[0], x_model[1], 0.0]) / np.hypot(x_model[0], x_model[1])
    y_cam = np.array([0.0, 0.0, -1.0])
    T = np.eye(4)
    T[:3, :3] = np.column_stack([np.cross(y_cam, z_cam), y_cam, z_cam])
    T[:3, 3] = T_world_model[:3, 3] - distance * z_cam
    T[2, 3] = 1.0
    return T


def test_hospital_days_moves_a_few_objects_between_two_days() -> None:
    """hospital_days: one world, two runs a day apart from places more than 5 m apart, driving
    more than 15 m of the same corridor in the same direction; on day 2 one wheelchair, one
    cart and one chair stand elsewhere (same ids, more than 1 m away), everything else as on
    day 1; the day-2 world renders the moved objects at their new places only."""
    from wardmap.sim.scenarios import DAY_S, DAYS_MOVED
    from wardmap.sim.sensors import SensorSimulator

    scene = build_scene("hospital_days", 4)
    day_1, day_2 = scene.robots
    assert (day_1.name, day_2.name) == ("day_1", "day_2")
    assert day_1.world is None and day_2.world is not None
    assert day_2.track.t[0] - day_1.track.t[-1] > 0.5 * DAY_S
    assert np.hypot(day_2.track.x[0] - day_1.track.x[0], day_2.track.y[0] - day_1.track.y[0]) > 5.0
    # Same corridor, same direction: day-2 samples within 0.3 m and 20 deg of a day-1 sample.
    p1 = np.column_stack([day_1.track.x, day_1.track.y])[::10]
    p2 = np.column_stack([day_2.track.x, day_2.track.y])[::10]
    close = np.linalg.norm(p2[:, None] - p1[None], axis=2) < 0.3
    dyaw = np.abs(np.angle(np.exp(1j * (day_2.track.yaw[::10, None] - day_1.track.yaw[None, ::10]))))
    assert (close & (dyaw < np.radians(20))).any(axis=1).sum() * 0.1 > 15.0

    w1, w2 = scene.world, scene.world_of(day_2)
    assert [o.id for o in w1.objects] == [o.id for o in w2.objects]
    moved = [(a, b) for a, b in zip(w1.objects, w2.objects, strict=True)
             if not np.array_equal(a.T_world_model, b.T_world_model)]
    assert sorted(a.cls for a, _ in moved) == sorted(DAYS_MOVED)
    for a, b in moved:
        assert np.linalg.norm(a.T_world_object[:2, 3] - b.T_world_object[:2, 3]) > 1.0
        assert b.note == "moved" and np.allclose(a.size, b.size)
    assert len(w1.static) == len(w2.static)

    rng = np.random.default_rng(0)
    render_1 = SensorSimulator(w1.static, w1.bank.stack())
    render_2 = SensorSimulator(w2.static, w2.bank.stack())
    for a, b in moved:
        old, new = _looking_at(a.T_world_model), _looking_at(b.T_world_model)
        assert (render_1.capture(old, None, 1.0, rng).labels == a.id).sum() > 500
        assert (render_2.capture(old, None, 1.0, rng).labels == a.id).sum() == 0
        assert (render_2.capture(new, None, 1.0, rng).labels == a.id).sum() > 500
