"""The associator's incremental API and its three methods on a synthetic scene with known truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from factories import CAMERA, MeasurementFactory, camera_looking_along_y, object_pose

from wardmap.server.association.associator import AssociationConfig, Associator
from wardmap.server.association.geometry import cut_at_side, cut_at_top_or_bottom
from wardmap.server.association.types import LandmarkChange
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.config import from_mapping
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.tools.evaluate import score_landmarks

DOOR = np.array([0.06, 1.16, 2.18])


def _scene(make: MeasurementFactory, n_keyframes: int = 14, seed: int = 0) -> list[tuple[list, np.ndarray]]:
    """A camera sliding along x past four identical chairs 0.55 m apart and a door pair
    (1.24 m apart), 4 cm measurement noise. Returns (measurements, T_world_camera) per keyframe."""
    rng = np.random.default_rng(seed)
    objects = [(k + 1, "chair", object_pose(0.55 * k, 3.0), None) for k in range(4)]
    door_yaw = np.pi / 2
    objects += [(10, "door", object_pose(-1.5, 4.0, 1.09, door_yaw), DOOR),
                (11, "door", object_pose(-0.26, 4.0, 1.09, door_yaw), DOOR)]
    out = []
    for i in range(n_keyframes):
        T = camera_looking_along_y(-1.0 + 0.15 * i)
        ms = []
        for gid, cat, T_wo, size in objects:
            kwargs = {"size": size} if size is not None else {}
            try:
                ms.append(make(T_wo, T, category=cat, gt=gid, keyframe=f"kf{i}", stamp=float(i),
                               offset=tuple(rng.normal(0, 0.04, 3)), **kwargs))
            except ValueError:
                continue
        out.append((ms, T))
    return out


def _run(cfg: AssociationConfig, scene: list) -> tuple[Associator, list[list[LandmarkChange]]]:
    assoc = Associator(cfg)
    changes = [assoc.add_keyframe(ms, T, CAMERA) for ms, T in scene]
    changes.append(assoc.flush())
    return assoc, changes


@pytest.mark.parametrize("method", ["hierarchical", "per_keyframe_hdp", "nearest"])
def test_every_measurement_in_exactly_one_landmark(make_measurement: MeasurementFactory, method: str) -> None:
    """Whatever the method, each measurement given ends in one landmark and nothing is lost."""
    scene = _scene(make_measurement)
    assoc, _ = _run(AssociationConfig(method=method), scene)  # type: ignore[arg-type]
    given = [id(m) for ms, _ in scene for m in ms]
    held = [id(m) for lm in assoc.landmarks() for m in lm.measurements]
    assert sorted(given) == sorted(held)
    for lm in assoc.landmarks():
        assert len({m.keyframe for m in lm.measurements}) == len(lm.measurements)  # one per keyframe
        assert {m.category for m in lm.measurements} == {lm.category}


def test_hierarchical_gets_identical_neighbours_right(make_measurement: MeasurementFactory) -> None:
    """Four identical chairs in a row and two identical doors: six landmarks, all measurements right."""
    assoc, _ = _run(AssociationConfig(), _scene(make_measurement))
    score = score_landmarks(assoc.landmarks())
    assert score.accuracy == 1.0
    assert score.landmarks == score.gt_objects == 6


def test_changes_arrive_when_a_group_completes(make_measurement: MeasurementFactory) -> None:
    """M = 4, j = 1: nothing before keyframe 3, then every 3 keyframes; flush handles the rest."""
    cfg = from_mapping(AssociationConfig, {"group_size": 4, "group_overlap": 1})
    scene = _scene(make_measurement, n_keyframes=9)
    assoc, changes = _run(cfg, scene)
    nonempty = [i for i, c in enumerate(changes[:-1]) if c]
    assert nonempty == [3, 6]
    assert all(c.kind == "created" for c in changes[3])
    assert changes[-1]  # keyframes 7, 8 come with the flush
    assert assoc.pending_keyframes == 0


def test_per_keyframe_hdp_pose_is_the_first_measurement(make_measurement: MeasurementFactory) -> None:
    """HDP-SLAM baseline: the landmark pose is its first measurement's pose."""
    assoc, _ = _run(AssociationConfig(method="per_keyframe_hdp"), _scene(make_measurement))
    for lm in assoc.landmarks():
        np.testing.assert_array_equal(lm.T_world_object, lm.measurements[0].T_world_object)


def test_nearest_joins_within_the_gate(make_measurement: MeasurementFactory) -> None:
    """The nearest baseline: the same chair seen twice (2 cm apart) is one landmark; 1 m apart, two."""
    T = camera_looking_along_y(0.0)
    assoc = Associator(AssociationConfig(method="nearest"))
    assoc.add_keyframe([make_measurement(object_pose(0, 3), T)], T, CAMERA)
    ch = assoc.add_keyframe([make_measurement(object_pose(0.02, 3), T)], T, CAMERA)
    assert [c.kind for c in ch] == ["updated"]
    ch = assoc.add_keyframe([make_measurement(object_pose(1.0, 3), T)], T, CAMERA)
    assert [c.kind for c in ch] == ["created"]
    assert len(assoc.landmarks()) == 2


def test_hierarchical_is_deterministic(make_measurement: MeasurementFactory) -> None:
    """Same input, same seed: identical landmarks."""
    scene = _scene(make_measurement, seed=5)
    a, _ = _run(AssociationConfig(seed=3), scene)
    b, _ = _run(AssociationConfig(seed=3), scene)
    assert [[id(m) for m in lm.measurements] for lm in a.landmarks()] == \
        [[id(m) for m in lm.measurements] for lm in b.landmarks()]


@pytest.mark.parametrize("method", ["hierarchical", "per_keyframe_hdp", "nearest"])
def test_bounded_memory_associates_the_same(make_measurement: MeasurementFactory, method: str) -> None:
    """keep_measurements off (the server): the same landmarks, poses, sizes and confidences as
    keeping everything, with at most max_history measurements held per landmark (plus what one
    update adds), without their appearance, every update's changes still carrying the
    measurements it added as given, and n_measurements counting them all."""
    scene = _scene(make_measurement, n_keyframes=30, seed=2)
    given = {id(m) for ms, _ in scene for m in ms}
    assert all(m.color_hist.size for ms, _ in scene for m in ms)
    full, _ = _run(AssociationConfig(method=method, max_history=4), scene)  # type: ignore[arg-type]
    cfg = AssociationConfig(method=method, max_history=4, keep_measurements=False)  # type: ignore[arg-type]
    bounded = Associator(cfg)
    seen: dict[int, list[tuple]] = {}

    def key(m: ObjectMeasurement) -> tuple:  # held copies lose their appearance, not these
        return (m.keyframe, tuple(m.box_xyxy), m.category)

    for ms, T in [*scene, ([], None)]:
        changes = bounded.add_keyframe(ms, T, CAMERA) if T is not None else bounded.flush()
        for c in changes:
            assert all(id(m) in given for m in c.added)  # as given, with their appearance
            held = [key(m) for m in c.landmark.measurements]
            assert all(m.color_hist.size == 0 and m.descriptors.size == 0 for m in c.landmark.measurements)
            old = seen.setdefault(c.landmark.id, [])
            added = c.landmark.n_measurements - len(old)
            assert 0 < added <= len(held)  # the update's new measurements are all there
            old.extend(held[len(held) - added:])
    a, b = full.landmarks(), bounded.landmarks()
    assert [lm.id for lm in a] == [lm.id for lm in b]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.T_world_object, y.T_world_object)
        np.testing.assert_array_equal(x.size, y.size)
        assert x.confidence == pytest.approx(y.confidence)
        assert y.n_measurements == x.n_measurements == len(x.measurements)
        assert seen[y.id] == [key(m) for m in x.measurements]  # every measurement was handed out once
    assert max(len(lm.measurements) for lm in b) < max(lm.n_measurements for lm in b)
    assert len(bounded._owner) < len(full._owner)


def test_bad_input_and_config(make_measurement: MeasurementFactory) -> None:
    assoc = Associator()
    with pytest.raises(GeometryError, match="T_world_camera"):
        assoc.add_keyframe([], np.eye(3), CAMERA)
    with pytest.raises(GeometryError, match="ObjectMeasurement"):
        assoc.add_keyframe(["chair"], np.eye(4), CAMERA)  # type: ignore[list-item]
    with pytest.raises(ConfigError, match="group_overlap"):
        from_mapping(AssociationConfig, {"group_size": 3, "group_overlap": 3})
    with pytest.raises(ConfigError, match="method"):
        from_mapping(AssociationConfig, {"method": "magic"})
    with pytest.raises(ConfigError, match="unknown key"):
        from_mapping(AssociationConfig, {"hdp": {"sigma": 1.0}})


def test_example_config_is_the_defaults() -> None:
    """deploy/association.toml loads and equals the dataclass defaults (documented values are true)."""
    from pathlib import Path

    from wardmap.shared.config import load_config
    from wardmap.tools.offline_map import MapConfig

    path = Path(__file__).resolve().parents[3] / "deploy" / "association.toml"
    assert load_config(AssociationConfig, path, section="association") == AssociationConfig()
    assert load_config(MapConfig, path, section="map") == MapConfig()


def test_interleaved_streams_share_landmarks(make_measurement: MeasurementFactory) -> None:
    """Two robots' keyframes arrive interleaved: groups form per stream (M = 3, j = 1: the
    first group of each completes at its third keyframe), and both robots' views of the
    same objects end in the same six landmarks."""
    cfg = from_mapping(AssociationConfig, {"group_size": 3, "group_overlap": 1})
    a, b = _scene(make_measurement, seed=1), _scene(make_measurement, seed=2)
    assoc = Associator(cfg)
    first_changes = []
    for k in range(len(a)):
        for name, scene in (("robot_a/1", a), ("robot_b/1", b)):
            ch = assoc.add_keyframe(scene[k][0], scene[k][1], CAMERA, stream=name)
            if ch and not first_changes:
                first_changes.append((k, name))
    assoc.flush()
    assert first_changes == [(2, "robot_a/1")]
    score = score_landmarks(assoc.landmarks())
    assert score.accuracy == 1.0 and score.landmarks == 6
    assert score.measurements == sum(len(ms) for ms, _ in a + b)


@pytest.mark.parametrize("method", ["hierarchical", "per_keyframe_hdp", "nearest"])
def test_flat_slivers_at_the_side_of_the_view_stay_unconfirmed(make_measurement: MeasurementFactory,
                                                               method: str) -> None:
    """A "cabinet" seen only as a flat sliver cut by the left image border (a wall taken for a
    cabinet) is kept but not confirmed, and not counted as an object; a door seen the same way,
    or a cabinet cut by the border with depth, is confirmed; a whole view confirms the sliver's
    landmark."""
    T = camera_looking_along_y(0.0)
    flat, deep = np.array([0.3, 0.02, 0.6]), np.array([0.8, 0.45, 1.7])
    cut = np.array([0.0, 180.0, 40.0, 420.0])  # touches the left border of the 640 px image

    def seen(x: float, category: str, size: np.ndarray, k: int, box: np.ndarray | None = cut):
        m = make_measurement(object_pose(x, 3.0), T, category=category, size=size, gt=None,
                             keyframe=f"kf{k}", stamp=float(k))
        return m if box is None else replace(m, box_xyxy=box)

    def landmarks(keyframes: list[list[ObjectMeasurement]]) -> dict[str, bool]:
        assoc = Associator(AssociationConfig(method=method))  # type: ignore[arg-type]
        for ms in keyframes:
            assoc.add_keyframe(ms, T, CAMERA)
        assoc.flush()
        return {lm.category: lm.confirmed for lm in assoc.landmarks()}

    door = np.array([0.3, 0.02, 2.0])  # a door's height (min_height_m), a sliver's width and depth
    slivers = [[seen(-1.0, "cabinet", flat, k), seen(0.0, "door", door, k), seen(1.0, "cart", deep, k)]
               for k in range(3)]
    assert landmarks(slivers) == {"cabinet": False, "door": True, "cart": True}
    whole = [seen(-1.0, "cabinet", flat, 3, box=None)]
    assert landmarks([*slivers, whole])["cabinet"] is True
    assoc = Associator(AssociationConfig(method=method))  # type: ignore[arg-type]
    for ms in slivers:
        assoc.add_keyframe(ms, T, CAMERA)
    assoc.flush()
    score = score_landmarks(assoc.landmarks())
    assert (score.landmarks, score.unconfirmed) == (2, 1)


def _confirmed_by_object(scene: list[list[ObjectMeasurement]], T: np.ndarray,
                         cfg: AssociationConfig) -> dict[int, bool]:
    """Associate ``scene`` (one list of measurements per keyframe, all seen from ``T``):
    ground-truth id of each landmark's first measurement -> whether the landmark is confirmed."""
    assoc = Associator(cfg)
    for ms in scene:
        assoc.add_keyframe(ms, T, CAMERA)
    assoc.flush()
    return {lm.gt_instances[0]: lm.confirmed for lm in assoc.landmarks()}


@pytest.mark.parametrize("method", ["hierarchical", "per_keyframe_hdp", "nearest"])
def test_a_whole_view_narrower_than_any_object_of_its_class_does_not_confirm(
        make_measurement: MeasurementFactory, method: str) -> None:
    """A "door" 0.28 m wide and a "bed" 0.2 m wide, both clear of the image borders (a door frame,
    a strip of wall), stay unconfirmed; a real door and bed beside them are confirmed; with
    ``min_width_m`` empty all four are."""
    T = camera_looking_along_y(0.0)
    kinds = [(-2.5, "door", np.array([0.28, 0.05, 1.1]), 1), (-1.4, "door", np.array([0.95, 0.05, 2.1]), 2),
             (0.0, "bed", np.array([0.2, 0.05, 0.75]), 3), (1.8, "bed", np.array([2.0, 0.95, 0.6]), 4)]
    scene = [[make_measurement(object_pose(x, 5.5, size[2] / 2), T, category=cat, size=size, gt=gt,
                               keyframe=f"kf{k}", stamp=float(k)) for x, cat, size, gt in kinds]
             for k in range(3)]
    for ms in scene:
        assert not any(cut_at_side(m.box_xyxy, CAMERA, 3.0) for m in ms)

    def confirmed(cfg: AssociationConfig) -> dict[int, bool]:
        return _confirmed_by_object(scene, T, cfg)

    default = AssociationConfig(method=method)  # type: ignore[arg-type]
    assert confirmed(default) == {1: False, 2: True, 3: False, 4: True}
    assert confirmed(replace(default, min_width_m=())) == {1: True, 2: True, 3: True, 4: True}


@pytest.mark.parametrize("method", ["hierarchical", "per_keyframe_hdp", "nearest"])
def test_a_whole_view_lower_than_any_door_does_not_confirm(make_measurement: MeasurementFactory,
                                                          method: str) -> None:
    """With ``min_height_m`` door 1.0 m, a "door" 0.55 x 0.66 m hung 1.55 m up (a poster),
    clear of every image border, stays unconfirmed; the same view cut by the bottom border
    cannot show the height and confirms; a real door beside it is confirmed; with
    ``min_height_m`` empty (the default) all are."""
    T = camera_looking_along_y(0.0)
    poster, door = np.array([0.55, 0.03, 0.66]), np.array([0.95, 0.05, 2.1])
    kinds = [(-1.5, 1.55, poster, 1), (1.0, 1.05, door, 2), (3.0, 1.55, poster, 3)]
    scene = [[make_measurement(object_pose(x, 5.5, z), T, category="door", size=size, gt=gt,
                               keyframe=f"kf{k}", stamp=float(k)) for x, z, size, gt in kinds]
             for k in range(3)]
    for ms in scene:
        assert not any(cut_at_side(m.box_xyxy, CAMERA, 3.0) or cut_at_top_or_bottom(m.box_xyxy, CAMERA, 3.0)
                       for m in ms)
        x1, y1, x2, _ = ms[2].box_xyxy
        ms[2] = replace(ms[2], box_xyxy=np.array([x1, y1, x2, float(CAMERA.height)]))  # cut at the bottom

    def confirmed(cfg: AssociationConfig) -> dict[int, bool]:
        return _confirmed_by_object(scene, T, cfg)

    default = AssociationConfig(method=method)  # type: ignore[arg-type]
    assert confirmed(replace(default, min_height_m=(("door", 1.0),))) == {1: False, 2: True, 3: True}
    assert default.min_height_m == () and confirmed(default) == {1: True, 2: True, 3: True}


@pytest.mark.parametrize("method", ["hierarchical", "per_keyframe_hdp", "nearest"])
def test_a_view_wider_than_any_object_of_its_class_does_not_confirm(
        make_measurement: MeasurementFactory, method: str) -> None:
    """A "chair" 0.69 m wide (the seats of two chairs; chairs are at most 0.6 m,
    ``HdpConfig.class_size_m``) stays unconfirmed, whole or cut by the border; a chair beside
    it is confirmed."""
    T = camera_looking_along_y(0.0)
    wide, chair = np.array([0.69, 0.31, 0.14]), np.array([0.46, 0.46, 0.93])
    scene = [[make_measurement(object_pose(-0.8, 3.0, 0.4), T, size=wide, gt=1, keyframe=f"kf{k}",
                               stamp=float(k)),
              make_measurement(object_pose(0.8, 3.0), T, size=chair, gt=2, keyframe=f"kf{k}", stamp=float(k))]
             for k in range(3)]
    scene[2][0] = replace(scene[2][0], box_xyxy=np.array([0.0, 300.0, 120.0, 420.0]))  # cut, 31 cm deep
    assoc = Associator(AssociationConfig(method=method))  # type: ignore[arg-type]
    for ms in scene:
        assoc.add_keyframe(ms, T, CAMERA)
    assoc.flush()
    assert {lm.gt_instances[0]: lm.confirmed for lm in assoc.landmarks()} == {1: False, 2: True}


@pytest.mark.parametrize("method", ["hierarchical", "per_keyframe_hdp", "nearest"])
def test_measurements_beyond_max_range_are_counted_not_associated(make_measurement: MeasurementFactory,
                                                                  method: str) -> None:
    """A chair 6.5 m ahead of the camera is left out of every landmark and counted in
    ``beyond_range``; one 5.5 m ahead is associated; with ``max_range_m`` 7 m both are."""
    T = camera_looking_along_y(0.0)
    scene = [[make_measurement(object_pose(-1.0, 5.5), T, gt=1, keyframe=f"kf{k}", stamp=float(k)),
              make_measurement(object_pose(1.0, 6.5), T, gt=2, keyframe=f"kf{k}", stamp=float(k))]
             for k in range(3)]
    default = AssociationConfig(method=method)  # type: ignore[arg-type]
    for cfg, kept, far in ((default, {1}, 3), (replace(default, max_range_m=7.0), {1, 2}, 0)):
        assoc = Associator(cfg)
        for ms in scene:
            assoc.add_keyframe(ms, T, CAMERA)
        assoc.flush()
        assert {m.gt_instance for lm in assoc.landmarks() for m in lm.measurements} == kept
        assert assoc.beyond_range == far


def test_confirmation_config_is_checked() -> None:
    with pytest.raises(ConfigError, match="flat_m"):
        from_mapping(AssociationConfig, {"flat_m": -0.1})
    with pytest.raises(ConfigError, match="max_range_m"):
        from_mapping(AssociationConfig, {"max_range_m": 0.0})
    with pytest.raises(ValueError, match="confirm_classes: not knowledge-graph classes: unicorn"):
        Associator(AssociationConfig(confirm_classes=("cabinet", "unicorn")))
    with pytest.raises(ValueError, match="min_width_m: not knowledge-graph classes: unicorn"):
        Associator(AssociationConfig(min_width_m=(("door", 0.5), ("unicorn", 0.3))))
    with pytest.raises(ConfigError, match="min_width_m entries"):
        from_mapping(AssociationConfig, {"min_width_m": [["door", -0.5]]})
    with pytest.raises(ConfigError, match="min_width_m lists a class twice"):
        from_mapping(AssociationConfig, {"min_width_m": [["door", 0.5], ["door", 0.6]]})
    with pytest.raises(ValueError, match="min_height_m: not knowledge-graph classes: unicorn"):
        Associator(AssociationConfig(min_height_m=(("unicorn", 1.0),)))
    with pytest.raises(ConfigError, match="min_height_m entries"):
        from_mapping(AssociationConfig, {"min_height_m": [["door", -1.0]]})
    with pytest.raises(ConfigError, match="min_height_m lists a class twice"):
        from_mapping(AssociationConfig, {"min_height_m": [["door", 1.0], ["door", 1.2]]})


@pytest.mark.parametrize("method", ["hierarchical", "nearest"])
def test_landmark_size_is_not_shrunk_by_partial_views(make_measurement: MeasurementFactory,
                                                      method: str) -> None:
    """A cabinet seen whole in 4 of 12 keyframes and in part (smaller) in the others: its landmark
    has the whole cabinet's size (``full_extent_classes``); a chair seen mostly as its legs keeps
    its median width but the whole chair's height. ``size_percentile = 50``: the median."""
    cabinet, chair = object_pose(0.0, 3.5, 0.9), object_pose(1.5, 3.0)
    scene = []
    for i in range(12):
        T = camera_looking_along_y(0.7 + 0.02 * i, z=1.0)
        whole = i % 3 == 0
        ms = [make_measurement(cabinet, T, category="cabinet", gt=1, keyframe=f"kf{i}", stamp=float(i),
                               size=np.array([1.0, 0.5, 1.8]) if whole else np.array([0.6, 0.3, 1.2])),
              make_measurement(chair, T, gt=2, keyframe=f"kf{i}", stamp=float(i),
                               size=np.array([0.46, 0.46, 0.93]) if whole else np.array([0.44, 0.44, 0.4]))]
        scene.append((ms, T))
    sizes = {}
    for percentile in (90.0, 50.0):
        assoc, _ = _run(AssociationConfig(method=method, size_percentile=percentile), scene)  # type: ignore[arg-type]
        assert sorted(lm.category for lm in assoc.landmarks()) == ["cabinet", "chair"]
        sizes[percentile] = {lm.category: lm.size for lm in assoc.landmarks()}
    np.testing.assert_allclose(sizes[90.0]["cabinet"], [1.0, 0.5, 1.8])
    np.testing.assert_allclose(sizes[90.0]["chair"], [0.44, 0.44, 0.93])
    np.testing.assert_allclose(sizes[50.0]["cabinet"], [0.6, 0.3, 1.2])
    np.testing.assert_allclose(sizes[50.0]["chair"], [0.44, 0.44, 0.4])


def test_size_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="size_percentile must be in"):
        AssociationConfig(size_percentile=120.0)
    with pytest.raises(ValueError, match="full_extent_classes: not knowledge-graph classes: sofa"):
        Associator(AssociationConfig(full_extent_classes=("bed", "sofa")))


def test_a_door_cut_by_the_border_keeps_the_whole_view_sigma(make_measurement: MeasurementFactory) -> None:
    """One keyframe per group (HDP only): a door cut by the left image border and, in the next
    keyframe, a whole door 0.6 m to its right. With the partly-seen sigma (0.3 m) the GMM takes
    them for one door; a door completed beyond the border (``completed_when_cut``, the default)
    keeps the whole-view sigma (0.12 m) and they are two."""
    T = camera_looking_along_y(0.0)
    cut = make_measurement(object_pose(-2.4, 4.0, 1.09, np.pi / 2), T, category="door", size=DOOR, gt=1,
                           keyframe="kf0")
    whole = make_measurement(object_pose(-1.8, 4.0, 1.09, np.pi / 2), T, category="door", size=DOOR, gt=2,
                             keyframe="kf1", stamp=1.0)
    assert cut_at_side(cut.box_xyxy, CAMERA, 3.0) and not cut_at_side(whole.box_xyxy, CAMERA, 3.0)
    one_per_group = {"group_size": 1, "group_overlap": 0}
    counts = {}
    for completed in ((), ("door",)):
        cfg = from_mapping(AssociationConfig, {**one_per_group, "completed_when_cut": list(completed)})
        assoc, _ = _run(cfg, [([cut], T), ([whole], T)])
        counts[completed] = len(assoc.landmarks())
    assert counts == {(): 1, ("door",): 2}
    assert AssociationConfig().completed_when_cut == ("door",)
    with pytest.raises(ValueError, match="completed_when_cut: not knowledge-graph classes: gate"):
        Associator(AssociationConfig(completed_when_cut=("door", "gate")))


def test_another_robot_filling_a_landmark_while_a_group_is_open(make_measurement: MeasurementFactory) -> None:
    """Robot a's last group is still open (its overlap keyframes wait for the next group) while
    robot b adds more than ``max_history`` measurements of the same chair: the measurements a's
    group still holds leave the landmark's history, yet a's group is associated when it closes
    (it used to raise KeyError on their dropped entries) and every measurement ends in the one
    chair."""
    assoc = Associator(AssociationConfig(keep_measurements=False, max_history=20))

    def feed(stream: str, n: int) -> None:
        for i in range(n):
            T = camera_looking_along_y(0.01 * (i % 5))
            assoc.add_keyframe([make_measurement(object_pose(0.0, 3.0), T, gt=1)], T, CAMERA, stream=stream)

    feed("a", 7)
    feed("b", 30)
    assoc.flush("a")
    feed("a", 3)
    assoc.flush()
    (chair,) = assoc.landmarks()
    assert chair.category == "chair" and chair.n_measurements == 40
