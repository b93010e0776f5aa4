"""The server's mapping stage on real simulated keyframes and the packaged segmentation network:
stored keyframes become measurements and objects; a restart replays and does not duplicate."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from wardmap.server.association.associator import AssociationConfig, beyond_range
from wardmap.server.objectmap import ObjectMap
from wardmap.server.perception.models import PerceptionConfig
from wardmap.server.pipeline import (
    MapPipeline,
    PipelineConfig,
    PipelineCounters,
    pack_measurement,
    unpack_measurement,
)
from wardmap.server.store import SqliteKeyframeStore
from wardmap.shared import wire
from wardmap.shared.wire import Intrinsics, KeyframeMsg, Keypoints, PackedRaster, encode

MODEL = Path(__file__).resolve().parents[2] / "server" / "models" / "hospital_seg.onnx"
pytestmark = pytest.mark.skipif(not MODEL.is_file(), reason="the packaged segmentation network is not built")

FRAMES = (0, 8, 16, 24, 32, 40, 48, 56)
LAST: dict[str, int] = {}
HIST_SUMS: dict[int, np.ndarray] = {}  # the last run's per-landmark colour histogram sums


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


def _run(path: Path, keyframes: list[tuple[KeyframeMsg, bytes]], close_idle_s: float = 0.0,
         closures: int = 0, association: AssociationConfig | None = None,
         checkpoint_s: float = 0.0) -> tuple[dict[str, int], int, int]:
    """Run the stage until idle (and until it closed ``closures`` idle sessions); every object it
    wrote has a mean colour. Returns the map's categories, the stored measurements and the
    measurements replayed at start; ``LAST`` gets the associator's landmark count. Checkpoints
    are off unless ``checkpoint_s`` is given (these tests are about the full replay)."""
    with SqliteKeyframeStore.open(path) as store:
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
            landmarks = pipe._associator.landmarks()
            LAST["landmarks"] = len(landmarks)
            LAST["beyond_range"] = counters.beyond_range
            LAST["associated"] = sum(lm.n_measurements for lm in landmarks)
            LAST["held"] = max((len(lm.measurements) for lm in landmarks), default=0)
            LAST["most"] = max((lm.n_measurements for lm in landmarks), default=0)
            HIST_SUMS.clear()
            HIST_SUMS.update({k: np.asarray(v).copy() for k, v in pipe._hist_sum.items()})
            # Long-lived association state holds no masks or 3D points (memory).
            held = [m for lm in landmarks for m in lm.measurements]
            assert all(m.mask.size == 0 and len(m.points_camera) == 0 for m in held)
        finally:
            pipe.stop()
        with store.reading("test") as conn:
            n_meas = int(conn.execute("SELECT COUNT(*) FROM measurements").fetchone()[0])
            colours = conn.execute("SELECT color_r, color_g, color_b FROM objects").fetchall()
            # Every associated measurement is one observation, written once as landmarks grow
            # (measurements of a group still filling up wait for it).
            n_obs = int(conn.execute("SELECT COUNT(*) FROM observations").fetchone()[0])
            assert n_obs == LAST["associated"]
            assert conn.execute("SELECT COALESCE(SUM(n_observations), 0) FROM objects").fetchone()[0] == n_obs
            # Landmarks merged into others are gone from the map too.
            assert conn.execute("SELECT COUNT(*) FROM objects").fetchone()[0] == LAST["landmarks"]
        assert all(c is not None and 0 <= c <= 255 for row in colours for c in row)
        return objects.categories(), n_meas, counters.replayed


@pytest.fixture(scope="module")
def anchored() -> list[tuple[KeyframeMsg, bytes]]:
    return _keyframes(anchored=True)


def test_keyframes_become_objects_and_a_restart_replays(tmp_path: Path, anchored: list) -> None:
    db = tmp_path / "map.db"
    categories, n_meas, replayed = _run(db, anchored)
    assert replayed == 0  # a new file has nothing to replay
    assert n_meas > 0
    assert sum(categories.values()) > 0
    assert categories.get("person", 0) == 0  # moving classes never enter the map
    # Restart on the same file with nothing new: association is replayed from the stored
    # measurements; no keyframe is measured twice and the map keeps its objects.
    categories2, n_meas2, replayed2 = _run(db, [])
    assert n_meas2 == n_meas and replayed2 == n_meas
    assert categories2 == categories


def _objects(path: Path) -> list[tuple]:
    """The object map's rows (id, category, rounded pose and size, observations, colour)."""
    with SqliteKeyframeStore.open(path) as store, store.reading("test") as conn:
        cols = [r[1] for r in conn.execute("PRAGMA table_info(objects)")]
        rows = conn.execute("SELECT * FROM objects ORDER BY object_id").fetchall()
    out = []
    for row in rows:
        d = dict(zip(cols, row, strict=True))
        out.append(tuple(round(v, 6) if isinstance(v, float) else v for k, v in sorted(d.items())
                         if not k.endswith("_s")))
    return out


def test_a_restart_resumes_from_the_association_checkpoint(tmp_path: Path, anchored: list) -> None:
    """The stage saves its association state when it stops; a restart loads it and replays only
    the keyframes after it, and the map ends as if it had never stopped. A checkpoint of other
    settings, a corrupt one, or none (``checkpoint_s = 0``) means a full replay."""
    ref = tmp_path / "ref.db"
    _, n_ref, _ = _run(ref, anchored)
    expected = _objects(ref)
    hist_sums = dict(HIST_SUMS)
    assert expected and hist_sums

    def same_state() -> bool:
        return _objects(db) == expected and HIST_SUMS.keys() == hist_sums.keys() and all(
            np.allclose(HIST_SUMS[k], v) for k, v in hist_sums.items())

    db = tmp_path / "map.db"
    _, _, replayed = _run(db, anchored[:4], checkpoint_s=600.0)
    assert replayed == 0
    with SqliteKeyframeStore.open(db) as store, store.reading("test") as conn:
        at_4 = conn.execute("SELECT last_rowid, state FROM association_checkpoint").fetchone()
    assert at_4[0] == 4
    _, n_all, replayed = _run(db, anchored[4:], checkpoint_s=600.0)  # 4 new keyframes in the backlog
    assert replayed == 0 and n_all == n_ref and same_state()
    _, _, replayed = _run(db, [], checkpoint_s=600.0)  # stopped at keyframe 8: nothing to replay
    assert replayed == 0 and same_state()

    def set_checkpoint(last_rowid: int, state: bytes) -> None:
        with SqliteKeyframeStore.open(db) as store, store.writing("test") as conn:
            conn.execute("UPDATE association_checkpoint SET last_rowid = ?, state = ?", (last_rowid, state))

    set_checkpoint(*at_4)  # as if the stage had crashed after keyframe 4
    _, _, replayed = _run(db, [], checkpoint_s=600.0)
    assert 0 < replayed < n_ref and same_state()
    set_checkpoint(8, b"\x00\xff")  # unreadable
    _, _, replayed = _run(db, [], checkpoint_s=600.0)
    assert replayed == n_ref and same_state()
    _, _, replayed = _run(db, [])  # checkpoints off
    assert replayed == n_ref and same_state()
    _, _, replayed = _run(db, [], association=AssociationConfig(group_size=5), checkpoint_s=600.0)
    assert replayed == n_ref  # a checkpoint of other settings is not used


def test_a_closure_stored_after_the_checkpoint_is_replayed(tmp_path: Path, anchored: list) -> None:
    """A session closed at the checkpoint's cursor after the checkpoint was written (the stage
    then crashed) is closed on restart, as a full replay closes it; one the checkpoint already
    holds changes nothing on the next restart."""
    import shutil

    db = tmp_path / "map.db"
    _run(db, anchored[:4], checkpoint_s=600.0)
    with SqliteKeyframeStore.open(db) as store, store.writing("test") as conn:
        conn.execute("INSERT INTO closed_sessions (robot_id, session_id, at_rowid) VALUES ('r1', 's1', 4)")
    full = tmp_path / "full.db"
    shutil.copy(db, full)
    _, _, replayed_full = _run(full, [])
    _, _, replayed = _run(db, [], checkpoint_s=600.0)
    assert replayed == 0 < replayed_full
    assert _objects(db) == _objects(full)
    with SqliteKeyframeStore.open(db) as store, store.reading("test") as conn:
        assert conn.execute("SELECT COUNT(*) FROM closed_sessions").fetchone()[0] == 1
    before = _objects(db)
    _, _, replayed = _run(db, [], checkpoint_s=600.0)  # the new checkpoint holds the closure
    assert replayed == 0 and _objects(db) == before


def test_replay_reads_no_keyframe_payload_and_backfills_old_stores(tmp_path: Path, anchored: list) -> None:
    """A restart replays from mapped_keyframes + measurements: with every payload blanked the map
    comes back the same. A store from before mapped_keyframes (rows deleted) is backfilled from
    the payloads once, and replays the same map too."""
    db = tmp_path / "map.db"
    categories, n_meas, _ = _run(db, anchored)
    landmarks = LAST["landmarks"]
    assert landmarks > 0
    with SqliteKeyframeStore.open(db) as store, store.writing("test") as conn:
        rows = conn.execute("SELECT seq, T_map_camera IS NOT NULL FROM mapped_keyframes ORDER BY seq")
        rows = rows.fetchall()
        assert [tuple(r) for r in rows] == [(i, 1) for i in range(len(FRAMES))]
        conn.execute("DELETE FROM mapped_keyframes")
    categories2, _, replayed2 = _run(db, [])  # backfill from the payloads, then replay
    assert replayed2 == n_meas and categories2 == categories and LAST["landmarks"] == landmarks
    with SqliteKeyframeStore.open(db) as store, store.writing("test") as conn:
        assert conn.execute("SELECT COUNT(*) FROM mapped_keyframes").fetchone()[0] == len(FRAMES)
        conn.execute("UPDATE keyframes SET payload = x'00'")
    categories3, _, replayed3 = _run(db, [])
    assert replayed3 == n_meas and categories3 == categories and LAST["landmarks"] == landmarks


def _session_observations(db: Path, session: str) -> tuple[int, int]:
    """(observations, anchored measurements within association's ``max_range_m``) of one session
    in the store ``db``; the farther ones are stored but never mapped."""
    max_range = AssociationConfig().max_range_m
    with SqliteKeyframeStore.open(db) as store, store.reading("test") as conn:
        n_obs = conn.execute("SELECT COUNT(*) FROM observations WHERE session_id = ?",
                             (session,)).fetchone()[0]
        blobs = conn.execute("SELECT payload FROM measurements WHERE session_id = ? AND anchored = 1",
                             (session,)).fetchall()
    n_meas = sum(not beyond_range(unpack_measurement(bytes(b)), max_range) for (b,) in blobs)
    return int(n_obs), int(n_meas)


def test_a_new_session_maps_the_last_group_of_the_previous_one(tmp_path: Path, anchored: list) -> None:
    """Session s1's last keyframes form an incomplete group that waits for more; the robot's next
    session closes it, so every measurement of s1 reaches the map, also after a restart."""
    db = tmp_path / "map.db"
    _run(db, anchored)
    n_obs, n_meas = _session_observations(db, "s1")
    assert 0 < n_obs < n_meas  # the last group (keyframes after the first 6) is still open
    msg = dataclasses.replace(anchored[0][0], session_id="s3", seq=0)
    _run(db, [(msg, encode(msg))])
    assert _session_observations(db, "s1") == (n_meas, n_meas)
    landmarks = LAST["landmarks"]
    _, _, replayed = _run(db, [])
    assert replayed > n_meas and LAST["landmarks"] == landmarks
    assert _session_observations(db, "s1") == (n_meas, n_meas)


def test_an_idle_session_is_closed_and_replayed(tmp_path: Path, anchored: list) -> None:
    """A session that goes quiet for close_idle_s has its last group mapped without waiting for a
    new session; the closure is stored and a restart replays it: same landmarks, no closure
    again. Keyframes of the session that come later start a new group and are mapped too."""
    db = tmp_path / "map.db"
    first, later = anchored[:7], anchored[7:]
    _run(db, first, close_idle_s=0.3, closures=1)
    n_obs, n_meas = _session_observations(db, "s1")
    assert n_obs == n_meas > 0
    landmarks = LAST["landmarks"]
    with SqliteKeyframeStore.open(db) as store, store.reading("test") as conn:
        rows = conn.execute("SELECT robot_id, session_id, at_rowid FROM closed_sessions").fetchall()
    assert [tuple(r) for r in rows] == [("r1", "s1", 7)]
    _, _, replayed = _run(db, [], close_idle_s=0.0)  # replay alone repeats the closure
    assert replayed == n_meas + LAST["beyond_range"] and LAST["landmarks"] == landmarks
    assert _session_observations(db, "s1") == (n_meas, n_meas)
    _run(db, later, close_idle_s=0.3, closures=1)  # the session resumes, then goes quiet again
    n_obs, n_meas = _session_observations(db, "s1")
    assert n_obs == n_meas
    _, _, replayed = _run(db, [], close_idle_s=0.0)
    assert LAST["beyond_range"] > 0  # the scene has objects farther than max_range_m: stored, not mapped
    assert replayed == n_meas + LAST["beyond_range"] and _session_observations(db, "s1") == (n_meas, n_meas)


def test_a_session_waiting_in_the_backlog_is_not_idle(tmp_path: Path, anchored: list) -> None:
    """A session quiet on the associator's clock but with stored keyframes the stage has not
    reached yet (behind other robots' backlog) is not closed; once they are processed it is."""
    with SqliteKeyframeStore.open(tmp_path / "map.db") as store:
        msg, payload = anchored[0]
        store.insert(msg, payload, time.time())
        pipe = MapPipeline(store, ObjectMap(store), config=PipelineConfig(close_idle_s=1.0),
                           perception=PerceptionConfig())
        pipe._open_stream["r1"] = "r1/s1"
        pipe._last_seen["r1/s1"] = time.monotonic() - 5.0
        pipe._close_idle()  # cursor 0: the keyframe waits
        assert pipe.counters().closed_idle == 0 and pipe._open_stream == {"r1": "r1/s1"}
        with store.writing("test") as conn:
            conn.execute("INSERT INTO pipeline_cursor (name, last_rowid) VALUES ('mapping', 1) "
                         "ON CONFLICT(name) DO UPDATE SET last_rowid = 1")
        pipe._close_idle()
        assert pipe.counters().closed_idle == 1 and pipe._open_stream == {}
        with store.reading("test") as conn:
            assert conn.execute("SELECT robot_id, session_id, at_rowid FROM closed_sessions").fetchall() == [
                ("r1", "s1", 1)]


def test_the_live_associator_holds_only_recent_measurements(tmp_path: Path, anchored: list) -> None:
    """With max_history 2 the stage's associator keeps at most a few measurements per landmark,
    yet every associated measurement is written once as an observation, colours come from all
    of them, and a restart replays to the same landmarks."""
    db = tmp_path / "map.db"
    small = AssociationConfig(max_history=2)
    categories, n_meas, _ = _run(db, anchored, association=small)
    landmarks, associated = LAST["landmarks"], LAST["associated"]
    assert LAST["held"] < LAST["most"]  # older measurements were dropped from memory
    with SqliteKeyframeStore.open(db) as store, store.reading("test") as conn:
        colours = conn.execute("SELECT color_r, color_g, color_b FROM objects ORDER BY object_id").fetchall()
    _run(tmp_path / "full.db", anchored)
    with SqliteKeyframeStore.open(tmp_path / "full.db") as store, store.reading("test") as conn:
        n_full = conn.execute("SELECT COUNT(*) FROM observations").fetchone()[0]
    assert n_full == associated  # the same measurements reach the map as with everything held
    categories2, _, replayed = _run(db, [], association=small)
    assert replayed == n_meas and LAST["landmarks"] == landmarks and categories2 == categories
    with SqliteKeyframeStore.open(db) as store, store.reading("test") as conn:
        assert conn.execute("SELECT color_r, color_g, color_b FROM objects ORDER BY object_id").fetchall() \
            == colours


def test_wait_idle_waits_for_association_not_just_the_cursor(tmp_path: Path, anchored: list) -> None:
    """The cursor is committed before a keyframe is associated; idle means associated and written
    too (the flaky CI failure: the map was read between the two)."""
    with SqliteKeyframeStore.open(tmp_path / "map.db") as store:
        for msg, payload in anchored[:3]:
            store.insert(msg, payload, time.time())
        pipe = MapPipeline(store, ObjectMap(store), config=PipelineConfig(poll_s=0.05),
                           perception=PerceptionConfig())
        associate = pipe._associate

        def slow_associate(keyframes):  # type: ignore[no-untyped-def]
            time.sleep(0.4)
            associate(keyframes)

        pipe._associate = slow_associate  # type: ignore[method-assign]
        pipe.start()
        try:
            assert pipe.wait_idle(120.0)
            assert pipe.counters().mapped == 3
        finally:
            pipe.stop()


def test_sessions_without_map_pose_are_measured_not_mapped(tmp_path: Path) -> None:
    categories, n_meas, _ = _run(tmp_path / "map.db", _keyframes(anchored=False)[:3])
    assert n_meas > 0 and sum(categories.values()) == 0


def test_measurement_blob_round_trip(anchored: list) -> None:
    """Stored measurements come back equal, without their masks."""
    from wardmap.server.perception.instances import oracle_instances  # noqa: F401  (import check)
    from wardmap.server.perception.types import ObjectMeasurement

    m = ObjectMeasurement(
        keyframe="r1/s1/0", stamp=1.5, category="door", confidence=0.9,
        box_xyxy=np.array([1.0, 2.0, 30.0, 40.0]), mask=np.ones((4, 4), bool),
        points_camera=np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32),
        T_camera_object=np.eye(4), T_world_camera=np.eye(4), T_world_object=np.eye(4),
        size=np.array([1.0, 0.1, 2.0]), color_hist=np.full(8, 0.125, np.float32),
        descriptors=np.arange(64, dtype=np.uint8).reshape(2, 32), gt_instance=7,
    )
    back = unpack_measurement(pack_measurement(m))
    assert back.mask.shape == (0, 0) and back.gt_instance == 7 and back.category == "door"
    for name in ("box_xyxy", "points_camera", "size", "color_hist", "descriptors", "T_world_object"):
        a, b = getattr(m, name), getattr(back, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name


def _counters_when_idle(store: SqliteKeyframeStore, config: PipelineConfig, segmenter: object
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
    with SqliteKeyframeStore.open(tmp_path / "map.db") as store:
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
        with SqliteKeyframeStore.open(tmp_path / f"{kf[0].session_id}.db") as store:
            store.insert(kf[0], kf[1], time.time())
            c = _counters_when_idle(store, PipelineConfig(poll_s=0.02), _WallChair())
            with store.reading("test") as conn:
                stored = int(conn.execute("SELECT COUNT(*) FROM measurements").fetchone()[0])
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
    from wardmap.server.api import _pipeline_metrics
    from wardmap.server.perception.measure import SKIP_KINDS

    depth = np.full((240, 320), 3.0, np.float32)
    depth[104:152, 148:168] = 2.9
    depth[16:64, 16:84] = 0.0
    msg, payload = _grey_keyframe(depth)
    with SqliteKeyframeStore.open(tmp_path / "m.db") as store:
        store.insert(msg, payload, time.time())
        c = _counters_when_idle(store, PipelineConfig(poll_s=0.02), _ChairAndHole())
    assert (c.processed, c.measurements, c.skipped) == (1, 1, {"little_depth": 1})
    text = _pipeline_metrics(c)
    samples = dict(line.rsplit(" ", 1) for line in text.splitlines() if not line.startswith("#"))
    name = "wardmap_mapping_instances_skipped_total"
    skipped = {k: v for k, v in samples.items() if k.startswith(name)}
    assert skipped == {f'{name}{{kind="{k}"}}': "1" if k == "little_depth" else "0" for k in SKIP_KINDS}
    assert f"# TYPE {name} counter" in text


def test_mapping_counters_in_prometheus_text() -> None:
    from wardmap.server.api import _pipeline_metrics

    text = _pipeline_metrics(PipelineCounters(5, 7, 4, 1, 0, 2, {"GeometryError": 1}, 3, closed_idle=1,
                                              floating=6, beyond_range=9, wall_pieces=4, floor_pieces=8))
    samples = dict(line.rsplit(" ", 1) for line in text.splitlines() if line and not line.startswith("#"))
    assert samples["wardmap_mapping_floating_left_out_total"] == "6"
    assert samples["wardmap_mapping_beyond_range_total"] == "9"
    assert samples["wardmap_mapping_wall_pieces_left_out_total"] == "4"
    assert samples["wardmap_mapping_floor_pieces_left_out_total"] == "8"
    assert samples["wardmap_mapping_keyframes_total"] == "5" and samples["wardmap_mapping_backlog"] == "2"
    assert samples['wardmap_mapping_failures_total{reason="GeometryError"}'] == "1"
    assert "# TYPE wardmap_mapping_floating_left_out_total counter" in text
