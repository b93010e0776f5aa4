"""The server's mapping stage (``wardmap.server.mapping.stage``) on real simulated keyframes and
the packaged segmentation network: stored keyframes become measurements and objects; a restart
replays and does not duplicate.

Tests that tamper with the database (to make it look like an older version's, or to blank the
keyframe payloads) open the SQLite file directly; everything else goes through the store."""

from __future__ import annotations

import dataclasses
import sqlite3
import time
from contextlib import closing
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from wardmap.server.association.associator import AssociationConfig, beyond_range
from wardmap.server.backend.core import BackendConfig
from wardmap.server.backend.stage import BackendStage
from wardmap.server.decoded import DEFAULT_MAX_BYTES, DecodedCache, DecodedCounters, keyframe_key
from wardmap.server.mapping import MappedKeyframe, MapPipeline, MapWriter, PipelineConfig, PipelineCounters
from wardmap.server.mapping.stage import CURSOR_NAME
from wardmap.server.objectmap import MAX_LIMIT, ObjectMap
from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.store import GraphChange, MappedPose, MapStore, SqliteMapStore
from wardmap.shared import wire
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.wire import Intrinsics, KeyframeMsg, Keypoints, PackedRaster, encode

MODEL = Path(__file__).resolve().parents[3] / "server" / "models" / "hospital_seg.onnx"
pytestmark = pytest.mark.skipif(not MODEL.is_file(), reason="the packaged segmentation network is not built")

FRAMES = (0, 8, 16, 24, 32, 40, 48, 56)


def _keyframes(anchored: bool) -> list[tuple[KeyframeMsg, bytes]]:
    from wardmap.sim.live import LiveRun

    live = LiveRun("ward_chairs", 0, frames=FRAMES[-1] + 1)
    T_world_odom = live.T_world_odom()
    out = []
    for seq, i in enumerate(FRAMES):
        f = live.frame(i)
        assert f.T_world_camera is not None
        ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        empty = Keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.int16), np.zeros(0, np.float32),
                          np.zeros(0, np.float32), np.zeros((0, 32), np.uint8))
        msg = KeyframeMsg(
            robot_id="r1", session_id="s1" if anchored else "s2", seq=seq, stamp=f.stamp,
            T_odom_camera=np.linalg.inv(T_world_odom) @ f.T_world_camera, pose_source="rgb",
            keypoints=empty, rgb_jpeg=jpg.tobytes(),
            depth=PackedRaster(*wire.encode_depth(f.depth_m[::4, ::4])),
            intrinsics=Intrinsics.from_camera(live.calibration.rgb, 5000.0),
            T_map_odom=T_world_odom if anchored else None,
        )
        out.append((msg, encode(msg)))
    return out


@dataclass(frozen=True)
class Run:
    """What one run of the stage left (see :func:`_run`).

    Attributes:
        categories: the object map's count per category.
        measurements: measurements in the store.
        counters: the stage's counters when it was idle.
        landmarks: the writer's landmarks.
        associated: measurements its landmarks took in all.
        held: most measurements one landmark holds in memory.
        most: most measurements one landmark took.
        colour_sums: per landmark, the sum of its measurements' colour histograms.
    """

    categories: dict[str, int]
    measurements: int
    counters: PipelineCounters
    landmarks: int
    associated: int
    held: int
    most: int
    colour_sums: dict[int, np.ndarray]

    @property
    def replayed(self) -> int:
        return self.counters.replayed


def _all_objects(objects: ObjectMap) -> list:
    return [h.record for h in objects.query(include_unconfirmed=True, limit=MAX_LIMIT).hits]


def _run(path: Path, keyframes: list[tuple[KeyframeMsg, bytes]], close_idle_s: float = 0.0,
         closures: int = 0, association: AssociationConfig | None = None,
         checkpoint_s: float = 0.0) -> Run:
    """Run the stage until idle (and until it closed ``closures`` idle sessions); every object it
    wrote has a mean colour. Checkpoints are off unless ``checkpoint_s`` is given (these tests are
    about the full replay)."""
    with SqliteMapStore.open(path) as store:
        for msg, payload in keyframes:
            store.insert(msg, payload, time.time())
        objects = ObjectMap(store)
        config = PipelineConfig(poll_s=0.05, close_idle_s=close_idle_s, checkpoint_s=checkpoint_s)
        pipe = MapPipeline(store, objects, config=config, perception=PerceptionConfig(),
                           association=association)
        pipe.start()
        try:
            assert pipe.wait_idle(120.0)
            deadline = time.monotonic() + 30.0
            while pipe.counters().closed_idle < closures and time.monotonic() < deadline:
                time.sleep(0.05)
            assert pipe.wait_idle(120.0)
            counters = pipe.counters()
            assert counters.closed_idle == closures
            landmarks = pipe.writer.landmarks()
            colour_sums = pipe.writer.colour_sums()
            # Long-lived association state holds no masks or 3D points (memory).
            held = [m for lm in landmarks for m in lm.measurements]
            assert all(m.mask.size == 0 and len(m.points_camera) == 0 for m in held)
        finally:
            pipe.stop()
        run = Run(objects.categories(), store.count_measurements(), counters, len(landmarks),
                  sum(lm.n_measurements for lm in landmarks),
                  max((len(lm.measurements) for lm in landmarks), default=0),
                  max((lm.n_measurements for lm in landmarks), default=0), colour_sums)
        records = _all_objects(objects)
        # Every associated measurement is one observation, written once as landmarks grow
        # (measurements of a group still filling up wait for it).
        n_obs = sum(store.observation_counts().values())
        assert n_obs == run.associated
        assert sum(r.n_observations for r in records) == n_obs
        # Landmarks merged into others are gone from the map too.
        assert len(records) == objects.count() == run.landmarks
        assert all(r.color_rgb is not None and all(0 <= c <= 255 for c in r.color_rgb) for r in records)
        return run


@pytest.fixture(scope="module")
def anchored() -> list[tuple[KeyframeMsg, bytes]]:
    return _keyframes(anchored=True)


def test_keyframes_become_objects_and_a_restart_replays(tmp_path: Path, anchored: list) -> None:
    db = tmp_path / "map.db"
    run = _run(db, anchored)
    assert run.replayed == 0  # a new file has nothing to replay
    assert run.measurements > 0
    assert sum(run.categories.values()) > 0
    assert run.categories.get("person", 0) == 0  # moving classes never enter the map
    # Restart on the same file with nothing new: association is replayed from the stored
    # measurements; no keyframe is measured twice and the map keeps its objects.
    again = _run(db, [])
    assert again.measurements == run.measurements and again.replayed == run.measurements
    assert again.categories == run.categories


def _decoded_run(path: Path, keyframes: list[tuple[KeyframeMsg, bytes]],
                 max_bytes: int) -> tuple[DecodedCounters, list[tuple]]:
    """Store ``keyframes`` and hand each decoded message to the stages' cache as ingest does,
    run the back-end and the mapping stage until idle; the cache's counters and the objects."""
    with SqliteMapStore.open(path) as store:
        cache = DecodedCache(max_bytes)
        pipe = MapPipeline(store, ObjectMap(store), config=PipelineConfig(poll_s=0.05, close_idle_s=0.0),
                           backend=BackendStage(store, decoded=cache))
        assert pipe.decoded is cache
        for msg, payload in keyframes:
            assert store.insert(msg, payload, time.time()) == "stored"
            cache.put(keyframe_key(msg), msg, len(payload))
        pipe.start()
        try:
            assert pipe.wait_idle(120.0)
        finally:
            pipe.stop()
        assert pipe.counters().processed == len(keyframes)
    return cache.counters(), _objects(path)


def test_each_keyframe_is_decoded_once_and_the_map_is_the_same(tmp_path: Path, anchored: list) -> None:
    """Keyframes ingest handed on are not decoded again: the back-end and the mapping stage take
    the message from the cache, the colour and depth are decoded once, and the mapping stage
    empties the cache. Without the cache (``max_bytes = 0``: each stage decodes the stored payload,
    counted) the object map comes out the same (poses to 1e-15 here: their last bits differed
    between the two modes, while two runs of one mode agreed exactly)."""
    n = len(anchored)
    once, objects_once = _decoded_run(tmp_path / "once.db", anchored, DEFAULT_MAX_BYTES)
    assert (once.put, once.hits, once.from_store) == (n, 2 * n, 0)
    assert (once.images_decoded, once.image_hits) == (n, n)
    assert (once.entries, once.nbytes, once.evicted) == (0, 0, 0)
    each, objects_each = _decoded_run(tmp_path / "each.db", anchored, 0)
    assert (each.hits, each.from_store, each.images_decoded) == (0, 2 * n, 2 * n)
    assert objects_once and [o[:3] + o[4:] for o in objects_once] == [o[:3] + o[4:] for o in objects_each]
    for a, b in zip(objects_once, objects_each, strict=True):  # T_world_object: the same but for rounding
        np.testing.assert_allclose(np.frombuffer(a[3]), np.frombuffer(b[3]), atol=1e-9)


def _objects(path: Path) -> list[tuple]:
    """The object map's objects by id (every field but the clock times; the pose exact, other
    floats rounded)."""
    with SqliteMapStore.open(path) as store:
        records = _all_objects(ObjectMap(store))
    out = []
    for r in records:
        values = [r.object_id, r.category, r.confidence, r.T_world_object.tobytes(), *r.position, *r.q_xyzw,
                  r.yaw, *r.size, *r.bounds_min, *r.bounds_max, *(r.color_rgb or (None,) * 3),
                  r.n_observations, r.robots, r.confirmed]
        out.append(tuple(round(v, 6) if isinstance(v, float) else v for v in values))
    return out


def _colours(path: Path) -> list[tuple[float, float, float] | None]:
    """The objects' mean colours, by object id."""
    with SqliteMapStore.open(path) as store:
        return [r.color_rgb for r in _all_objects(ObjectMap(store))]


def test_a_restart_resumes_from_the_association_checkpoint(tmp_path: Path, anchored: list) -> None:
    """The stage saves its association state when it stops; a restart loads it and replays only
    the keyframes after it, and the map ends as if it had never stopped. A checkpoint of other
    settings, a corrupt one, or none (``checkpoint_s = 0``) means a full replay."""
    ref = tmp_path / "ref.db"
    ref_run = _run(ref, anchored)
    n_ref, hist_sums = ref_run.measurements, ref_run.colour_sums
    expected = _objects(ref)
    assert expected and hist_sums

    def same_state(run: Run) -> bool:
        return _objects(db) == expected and run.colour_sums.keys() == hist_sums.keys() and all(
            np.allclose(run.colour_sums[k], v) for k, v in hist_sums.items())

    db = tmp_path / "map.db"
    assert _run(db, anchored[:4], checkpoint_s=600.0).replayed == 0
    with SqliteMapStore.open(db) as store:
        at_4 = store.checkpoint()
    assert at_4 is not None and at_4.last_rowid == 4
    run = _run(db, anchored[4:], checkpoint_s=600.0)  # 4 new keyframes in the backlog
    assert run.replayed == 0 and run.measurements == n_ref and same_state(run)
    run = _run(db, [], checkpoint_s=600.0)  # stopped at keyframe 8: nothing to replay
    assert run.replayed == 0 and same_state(run)

    def set_checkpoint(last_rowid: int, state: bytes) -> None:
        with SqliteMapStore.open(db) as store:
            saved = store.checkpoint()
            assert saved is not None
            store.save_checkpoint(replace(saved, last_rowid=last_rowid, state=state))

    set_checkpoint(at_4.last_rowid, at_4.state)  # as if the stage had crashed after keyframe 4
    run = _run(db, [], checkpoint_s=600.0)
    assert 0 < run.replayed < n_ref and same_state(run)
    set_checkpoint(8, b"\x00\xff")  # unreadable
    run = _run(db, [], checkpoint_s=600.0)
    assert run.replayed == n_ref and same_state(run)
    run = _run(db, [])  # checkpoints off
    assert run.replayed == n_ref and same_state(run)
    run = _run(db, [], association=AssociationConfig(group_size=5), checkpoint_s=600.0)
    assert run.replayed == n_ref  # a checkpoint of other settings is not used


def test_a_closure_stored_after_the_checkpoint_is_replayed(tmp_path: Path, anchored: list) -> None:
    """A session closed at the checkpoint's cursor after the checkpoint was written (the stage
    then crashed) is closed on restart, as a full replay closes it; one the checkpoint already
    holds changes nothing on the next restart."""
    import shutil

    db = tmp_path / "map.db"
    _run(db, anchored[:4], checkpoint_s=600.0)
    with SqliteMapStore.open(db) as store:
        store.close_sessions([("r1", "s1")], 4)
    full = tmp_path / "full.db"
    shutil.copy(db, full)
    replayed_full = _run(full, []).replayed
    replayed = _run(db, [], checkpoint_s=600.0).replayed
    assert replayed == 0 < replayed_full
    assert _objects(db) == _objects(full)
    with SqliteMapStore.open(db) as store:
        assert len(store.closed_sessions()) == 1
    before = _objects(db)
    replayed = _run(db, [], checkpoint_s=600.0).replayed  # the new checkpoint holds the closure
    assert replayed == 0 and _objects(db) == before


def _tamper(db: Path, sql: str) -> None:
    """Change the SQLite file behind the store's back (what an older version or a damaged
    payload leaves)."""
    with closing(sqlite3.connect(db)) as conn, conn:
        conn.execute(sql)


def test_replay_reads_no_keyframe_payload_and_backfills_old_stores(tmp_path: Path, anchored: list) -> None:
    """A restart replays from the keyframes' map poses + measurements: with every payload blanked the
    map comes back the same. A store from before map poses were kept (rows deleted) is backfilled
    from the payloads once, and replays the same map too."""
    db = tmp_path / "map.db"
    run = _run(db, anchored)
    assert run.landmarks > 0
    with SqliteMapStore.open(db) as store:
        on_map = store.anchored_keyframes(0, store.cursor(CURSOR_NAME), 100)
        assert [k.seq for k in on_map] == list(range(len(FRAMES)))
        assert store.unmapped_keyframes(len(FRAMES), 100) == []
    _tamper(db, "DELETE FROM mapped_keyframes")
    with SqliteMapStore.open(db) as store:
        assert len(store.unmapped_keyframes(len(FRAMES), 100)) == len(FRAMES)
    run2 = _run(db, [])  # backfill from the payloads, then replay
    assert run2.replayed == run.measurements and run2.categories == run.categories
    assert run2.landmarks == run.landmarks
    with SqliteMapStore.open(db) as store:
        assert store.unmapped_keyframes(len(FRAMES), 100) == []
        assert len(store.anchored_keyframes(0, len(FRAMES), 100)) == len(FRAMES)
    _tamper(db, "UPDATE keyframes SET payload = x'00'")
    run3 = _run(db, [])
    assert run3.replayed == run.measurements and run3.categories == run.categories
    assert run3.landmarks == run.landmarks


def test_erased_images_keep_the_map_and_the_keyframes_still_map(tmp_path: Path, anchored: list) -> None:
    """Retention past every keyframe of a mapped store: each image is erased, and a restart
    (back-end and mapping replay) brings back the same objects from the same poses. A store
    whose images were erased before mapping: the back-end puts every keyframe in its graph and
    the mapping stage processes each without a failure."""
    from wardmap.server.retention import ImageRetention

    db = tmp_path / "map.db"
    run = _run(db, anchored)
    objects = _objects(db)
    with SqliteMapStore.open(db) as store:
        trajectory = store.trajectory("r1")
        assert ImageRetention(store, 60.0, 3600.0).run_once(now_s=time.time() + 120.0) == len(FRAMES)
        assert all(store.images_erased_s("r1", "s1", k) is not None for k in range(len(FRAMES)))
        assert np.array_equal(store.trajectory("r1")[1], trajectory[1])
    assert _objects(db) == objects
    again = _run(db, [])
    assert again.categories == run.categories and again.landmarks == run.landmarks
    assert again.counters.failures == {} and again.counters.restarts == 0

    early = tmp_path / "early.db"
    with SqliteMapStore.open(early) as store:
        for msg, payload in anchored:
            store.insert(msg, payload, time.time())
        assert ImageRetention(store, 60.0, 3600.0).run_once(now_s=time.time() + 120.0) == len(FRAMES)
    blind = _run(early, [])
    assert blind.counters.failures == {} and blind.counters.restarts == 0
    assert blind.counters.processed == len(FRAMES)
    with SqliteMapStore.open(early) as store:
        nodes, _ = store.graph_records()
        assert len(nodes) == len(FRAMES)


def _session_observations(db: Path, session: str) -> tuple[int, int]:
    """(observations, anchored measurements within association's ``max_range_m``) of one session
    in the store ``db``; the farther ones are stored but never mapped."""
    max_range = AssociationConfig().max_range_m
    with SqliteMapStore.open(db) as store:
        objects = ObjectMap(store)
        n_obs = 0
        for record in _all_objects(objects):
            detail = objects.get(record.object_id, max_observations=1000)
            assert detail is not None
            n_obs += sum(o.session_id == session for o in detail.observations)
        measured = [m for kf in store.anchored_keyframes(0, store.cursor(CURSOR_NAME), 1000)
                    if kf.session_id == session for m in kf.measurements]
    n_meas = sum(not beyond_range(m, max_range) for m in measured)
    return n_obs, n_meas


def test_a_new_session_maps_the_last_group_of_the_previous_one(tmp_path: Path, anchored: list) -> None:
    """Session s1's last keyframes form an incomplete group that waits for more; the robot's next
    session closes it, so every measurement of s1 reaches the map, also after a restart."""
    db = tmp_path / "map.db"
    _run(db, anchored)
    n_obs, n_meas = _session_observations(db, "s1")
    assert 0 < n_obs < n_meas  # the last group (keyframes after the first 6) is still open
    msg = dataclasses.replace(anchored[0][0], session_id="s3", seq=0)
    landmarks = _run(db, [(msg, encode(msg))]).landmarks
    assert _session_observations(db, "s1") == (n_meas, n_meas)
    run = _run(db, [])
    assert run.replayed > n_meas and run.landmarks == landmarks
    assert _session_observations(db, "s1") == (n_meas, n_meas)


def test_an_idle_session_is_closed_and_replayed(tmp_path: Path, anchored: list) -> None:
    """A session that goes quiet for close_idle_s has its last group mapped without waiting for a
    new session; the closure is stored and a restart replays it: same landmarks, no closure
    again. Keyframes of the session that come later start a new group and are mapped too."""
    db = tmp_path / "map.db"
    first, later = anchored[:7], anchored[7:]
    landmarks = _run(db, first, close_idle_s=0.3, closures=1).landmarks
    n_obs, n_meas = _session_observations(db, "s1")
    assert n_obs == n_meas > 0
    with SqliteMapStore.open(db) as store:
        assert [(c.robot_id, c.session_id, c.at_rowid) for c in store.closed_sessions()] == [("r1", "s1", 7)]
    run = _run(db, [], close_idle_s=0.0)  # replay alone repeats the closure
    assert run.replayed == n_meas + run.counters.beyond_range and run.landmarks == landmarks
    assert _session_observations(db, "s1") == (n_meas, n_meas)
    _run(db, later, close_idle_s=0.3, closures=1)  # the session resumes, then goes quiet again
    n_obs, n_meas = _session_observations(db, "s1")
    assert n_obs == n_meas
    run = _run(db, [], close_idle_s=0.0)
    assert run.counters.beyond_range > 0  # the scene has objects farther than max_range_m: stored, not mapped
    assert run.replayed == n_meas + run.counters.beyond_range
    assert _session_observations(db, "s1") == (n_meas, n_meas)


class _Clock:
    """Monotonic seconds that move only when told."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_a_session_waiting_in_the_backlog_is_not_idle(tmp_path: Path, anchored: list) -> None:
    """A session quiet on the stage's clock but with stored keyframes the stage has not reached yet
    (behind other robots' backlog) is not closed; once they are processed it is."""
    with SqliteMapStore.open(tmp_path / "map.db") as store:
        msg, payload = anchored[0]
        store.insert(msg, payload, time.time())
        clock = _Clock()
        pipe = MapPipeline(store, ObjectMap(store), config=PipelineConfig(close_idle_s=1.0),
                           perception=PerceptionConfig(), clock=clock)
        camera = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
        pipe.associate([MappedKeyframe("r1/s1", np.eye(4), camera, [])])  # an earlier keyframe of r1/s1
        clock.now += 5.0
        assert pipe.close_idle() == []  # cursor 0: the keyframe waits
        assert pipe.counters().closed_idle == 0 and pipe.writer.open_streams == {"r1": "r1/s1"}
        store.commit_keyframe(CURSOR_NAME, 1, MappedPose("r1", "s1", 0, None, None), [], anchored=False)
        assert pipe.close_idle() == ["r1/s1"]
        assert pipe.counters().closed_idle == 1 and pipe.writer.open_streams == {}
        assert [(c.robot_id, c.session_id, c.at_rowid) for c in store.closed_sessions()] == [("r1", "s1", 1)]


def test_the_live_associator_holds_only_recent_measurements(tmp_path: Path, anchored: list) -> None:
    """With max_history 2 the stage's associator keeps at most a few measurements per landmark,
    yet every associated measurement is written once as an observation, colours come from all
    of them, and a restart replays to the same landmarks."""
    db = tmp_path / "map.db"
    small = AssociationConfig(max_history=2)
    run = _run(db, anchored, association=small)
    assert run.held < run.most  # older measurements were dropped from memory
    colours = _colours(db)
    full = tmp_path / "full.db"
    _run(full, anchored)
    with SqliteMapStore.open(full) as store:
        n_full = sum(store.observation_counts().values())
    assert n_full == run.associated  # the same measurements reach the map as with everything held
    again = _run(db, [], association=small)
    assert again.replayed == run.measurements and again.landmarks == run.landmarks
    assert again.categories == run.categories
    assert _colours(db) == colours


def test_wait_idle_waits_for_association_not_just_the_cursor(
        tmp_path: Path, anchored: list, monkeypatch: pytest.MonkeyPatch) -> None:
    """The cursor is committed before a keyframe is associated; idle means associated and written
    too (the flaky CI failure: the map was read between the two)."""
    associate = MapWriter.associate

    def slow_associate(self: MapWriter, keyframe: MappedKeyframe) -> int:
        time.sleep(0.4)
        return associate(self, keyframe)

    monkeypatch.setattr(MapWriter, "associate", slow_associate)
    with SqliteMapStore.open(tmp_path / "map.db") as store:
        for msg, payload in anchored[:3]:
            store.insert(msg, payload, time.time())
        pipe = MapPipeline(store, ObjectMap(store), config=PipelineConfig(poll_s=0.05),
                           perception=PerceptionConfig())
        pipe.start()
        try:
            assert pipe.wait_idle(120.0)
            assert pipe.counters().mapped == 3
        finally:
            pipe.stop()


def test_a_session_off_the_map_waits_and_its_objects_appear_once_it_is_anchored(tmp_path: Path) -> None:
    """A second session without a map pose is measured but not associated while the back-end
    has it floating; when the back-end anchors it (a graph commit with its estimates and a new
    map epoch, as :class:`BackendStage` makes), the mapping stage rebuilds the object map and
    the session's observations are on it, at the poses the back-end gave."""
    on_map = _keyframes(anchored=True)
    waiting = [(replace(m, robot_id="r2", session_id="day2"), encode(replace(m, robot_id="r2",
                                                                             session_id="day2")))
               for m, _ in _keyframes(anchored=False)]
    with SqliteMapStore.open(tmp_path / "map.db") as store:
        for msg, payload in on_map + waiting:
            store.insert(msg, payload, time.time())
        objects = ObjectMap(store)
        backend = BackendStage(store, BackendConfig(enabled=False), poll_s=0.05)  # no place recognition
        config = PipelineConfig(poll_s=0.05, close_idle_s=0.0, rebuild_min_s=0.0)
        pipe = MapPipeline(store, objects, config=config, perception=PerceptionConfig(), backend=backend)
        pipe.start()
        try:
            assert pipe.wait_idle(120.0)
            before = pipe.counters()
            assert before.unanchored == len(waiting) and before.rebuilds == 0
            assert not any(r.robots == ("r2",) or "r2" in r.robots for r in _all_objects(objects))
            assert not store.session_anchors()[1].T_map_odom is not None  # r2/day2 floats
            # The back-end anchors r2/day2 where r1/s1 is (the same frames, so the same poses).
            T_map = {m.seq: m.T_map_odom @ m.T_odom_camera for m, _ in on_map}
            store.commit_graph("test", 0, GraphChange(
                estimates=[(("r2", "day2", m.seq), T_map[m.seq]) for m, _ in waiting], bump_epoch=True))
            assert pipe.wait_idle(120.0)
            after = pipe.counters()
            assert after.rebuilds == 1
            seen_by_r2 = [r for r in _all_objects(objects) if "r2" in r.robots]
            assert seen_by_r2, "the anchored session's measurements reached the map"
        finally:
            pipe.stop()


def _counters_when_idle(store: MapStore, config: PipelineConfig, segmenter: object
                        ) -> PipelineCounters:
    """Run the stage with ``segmenter`` over the stored keyframes until idle; its counters."""
    pipe = MapPipeline(store, ObjectMap(store), config=config, segmenter=segmenter)
    pipe.start()
    try:
        assert pipe.wait_idle(30.0)
        return pipe.counters()
    finally:
        pipe.stop()


class _Flaky:
    """A segmenter (no instances) that raises an unexpected error on the given call numbers."""

    def __init__(self, failing_calls: set[int]) -> None:
        self.failing_calls = failing_calls
        self.calls = 0

    def __call__(self, bgr: np.ndarray, depth_m: np.ndarray | None) -> list:
        self.calls += 1
        if self.calls in self.failing_calls:
            raise RuntimeError(f"bug on call {self.calls}")
        return []


@pytest.mark.parametrize(
    ("failing", "processed", "skipped"),
    [({2}, 4, 0), ({2, 3, 4}, 3, 1)],
    ids=["recovers", "skips-after-3-attempts"],
)
def test_unexpected_errors_restart_with_backoff(
    tmp_path: Path, anchored: list, failing: set[int], processed: int, skipped: int
) -> None:
    """An unexpected error does not stop the stage: it backs off and resumes at its cursor; a
    keyframe that fails max_attempts times is skipped, counted as internal, and the rest go on."""
    with SqliteMapStore.open(tmp_path / "map.db") as store:
        for msg, payload in anchored[:4]:
            store.insert(msg, payload, time.time())
        cfg = PipelineConfig(poll_s=0.02, retry_s=0.01, max_retry_s=0.05, max_attempts=3)
        c = _counters_when_idle(store, cfg, _Flaky(failing))
    assert c.restarts == len(failing) and "RuntimeError: bug on call" in c.last_error
    assert c.processed == processed
    assert c.failures == ({"internal: RuntimeError": 1} if skipped else {})
    assert c.backlog == 0


@pytest.mark.parametrize("kwargs", [{"close_idle_s": -1.0}, {"close_idle_s": float("nan")}, {"batch": 0},
                                    {"max_attempts": 0}])
def test_bad_pipeline_config_is_rejected(kwargs: dict) -> None:
    from wardmap.shared.errors import ConfigError

    with pytest.raises(ConfigError):
        PipelineConfig(**kwargs)


def _grey_keyframe(depth: np.ndarray, session: str = "s", T_odom_camera: np.ndarray | None = None,
                   T_odom_base: np.ndarray | None = None) -> tuple[KeyframeMsg, bytes]:
    """One keyframe of a uniform grey image with ``depth`` (240, 320) metres, seen by a 320x240
    camera (depth sent at 1/4), no keypoints; returns the message and its payload."""
    from wardmap.shared.camera import PinholeCamera

    camera = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
    ok, jpg = cv2.imencode(".jpg", np.full((240, 320, 3), 128, np.uint8))
    assert ok
    empty = Keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.int16), np.zeros(0, np.float32),
                      np.zeros(0, np.float32), np.zeros((0, 32), np.uint8))
    msg = KeyframeMsg(robot_id="r1", session_id=session, seq=0, stamp=1.0,
                      T_odom_camera=np.eye(4) if T_odom_camera is None else T_odom_camera,
                      pose_source="rgb", keypoints=empty, rgb_jpeg=jpg.tobytes(),
                      depth=PackedRaster(*wire.encode_depth(depth[::4, ::4].astype(np.float32))),
                      intrinsics=Intrinsics.from_camera(camera, 5000.0), T_odom_base=T_odom_base)
    return msg, encode(msg)


class _WallChair:
    """A segmenter that finds one 'chair' 0.7-1.2 m up the wall (a fire extinguisher)."""

    def __call__(self, bgr: np.ndarray, depth_m: np.ndarray | None) -> list:
        from wardmap.server.perception.instances import box_of_mask
        from wardmap.server.perception.types import Instance

        mask = np.zeros(bgr.shape[:2], bool)
        mask[104:152, 148:168] = True
        return [Instance("chair", 0.9, mask, box_of_mask(mask))]


def test_a_chair_floating_above_the_floor_is_left_out_and_counted(tmp_path: Path) -> None:
    """A keyframe of a robot base (floor known) loses the chair on the wall and counts it in
    /metrics' counters; a hand-held camera's keyframe (no base, floor unknown) keeps it."""
    rows = (np.arange(240) - 119.5) / 262.5  # (v - cy) / fy of the keyframe's camera
    with np.errstate(divide="ignore"):
        depth = np.minimum(np.where(rows > 0, 1.05 / rows, np.inf), 3.0)[:, None] * np.ones((1, 320))
    depth[104:152, 148:168] = 2.9  # 10 cm in front of the wall 3 m ahead, floor below 212
    T_odom_camera = np.eye(4)
    T_odom_camera[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]  # level, along +x
    T_odom_camera[2, 3] = 1.05
    counts = []
    for kf in (_grey_keyframe(depth, "base", T_odom_camera, np.eye(4)),
               _grey_keyframe(depth, "handheld", T_odom_camera)):
        with SqliteMapStore.open(tmp_path / f"{kf[0].session_id}.db") as store:
            store.insert(kf[0], kf[1], time.time())
            c = _counters_when_idle(store, PipelineConfig(poll_s=0.02), _WallChair())
            stored = store.count_measurements()
        counts.append((c.processed, c.floating, c.measurements, stored))
    assert counts == [(1, 1, 0, 0), (1, 0, 1, 1)]


class _ChairAndHole(_WallChair):
    """The wall chair, and a 'cabinet' where the depth image has a hole."""

    def __call__(self, bgr: np.ndarray, depth_m: np.ndarray | None) -> list:
        from wardmap.server.perception.instances import box_of_mask
        from wardmap.server.perception.types import Instance

        hole = np.zeros(bgr.shape[:2], bool)
        hole[20:60, 20:80] = True
        return [*super().__call__(bgr, depth_m), Instance("cabinet", 0.9, hole, box_of_mask(hole))]


def test_instances_perception_cannot_measure_are_counted_by_kind(tmp_path: Path) -> None:
    """An instance on a depth hole is not measured: no measurement, one 'little_depth' skip in the
    counters and in /metrics (every kind has its line); the chair beside it is measured."""
    from wardmap.server.api.prometheus import exposition, pipeline_metrics
    from wardmap.server.perception.measure import SKIP_KINDS

    depth = np.full((240, 320), 3.0, np.float32)
    depth[104:152, 148:168] = 2.9
    depth[16:64, 16:84] = 0.0
    msg, payload = _grey_keyframe(depth)
    with SqliteMapStore.open(tmp_path / "m.db") as store:
        store.insert(msg, payload, time.time())
        c = _counters_when_idle(store, PipelineConfig(poll_s=0.02), _ChairAndHole())
    assert (c.processed, c.measurements, c.skipped) == (1, 1, {"little_depth": 1})
    text = exposition(pipeline_metrics(c))
    samples = {k: float(v) for k, v in (line.rsplit(" ", 1) for line in text.splitlines()
                                         if line and not line.startswith("#"))}
    name = "wardmap_mapping_instances_skipped_total"
    skipped = {k: v for k, v in samples.items() if k.startswith(name)}
    assert skipped == {f'{name}{{kind="{k}"}}': 1 if k == "little_depth" else 0 for k in SKIP_KINDS}
    assert f"# TYPE {name} counter" in text


def test_mapping_counters_in_prometheus_text() -> None:
    from wardmap.server.api.prometheus import exposition, pipeline_metrics

    c = PipelineCounters(5, 7, 4, 1, 0, 2, {"GeometryError": 1}, 3, closed_idle=1,
                         floating=6, beyond_range=9, wall_pieces=4, floor_pieces=8)
    text = exposition(pipeline_metrics(c))
    samples = {k: float(v) for k, v in (line.rsplit(" ", 1) for line in text.splitlines()
                                         if line and not line.startswith("#"))}
    assert samples["wardmap_mapping_floating_left_out_total"] == 6
    assert samples["wardmap_mapping_beyond_range_total"] == 9
    assert samples["wardmap_mapping_wall_pieces_left_out_total"] == 4
    assert samples["wardmap_mapping_floor_pieces_left_out_total"] == 8
    assert samples["wardmap_mapping_keyframes_total"] == 5 and samples["wardmap_mapping_backlog"] == 2
    assert samples['wardmap_mapping_failures_total{reason="GeometryError"}'] == 1
    assert "# TYPE wardmap_mapping_floating_left_out_total counter" in text
