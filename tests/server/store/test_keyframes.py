"""Tests of the server's SQLite keyframe store (``wardmap.server.store``).

Keyframes are real ``wardmap.shared.wire`` messages (a 64x48 JPEG, a 32x24 depth raster,
a few keypoints) encoded with :func:`wire.encode`. The crash test SIGKILLs a real child
process that is inserting; it synchronises on the lines the child writes after each
committed insert, never on sleeps.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import sqlite3
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from wardmap.server import store as store_mod
from wardmap.server.store import (
    MIGRATIONS,
    KeyframeRow,
    KeyframeStore,
    RobotSummary,
    SqliteKeyframeStore,
    StoreError,
    open_store,
)
from wardmap.shared import wire
from wardmap.shared.errors import WardmapError
from wardmap.shared.se3 import make_transform
from wardmap.shared.wire import Intrinsics, KeyframeMsg, Keypoints, PackedRaster

W, H = 64, 48
T0 = 1_714_557_600.0  # 2024-05-01 10:00 UTC


def _pose(stamp: float) -> np.ndarray:
    """A rigid pose that depends on ``stamp`` (yaw and translation), so values can be checked."""
    a = 0.1 * stamp
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return make_transform(R, [stamp % 7.0, -1.0, 0.5])


_BASE: KeyframeMsg | None = None


def base_keyframe() -> KeyframeMsg:
    """A valid tiny keyframe (built once; others are ``replace``d copies)."""
    global _BASE
    if _BASE is None:
        rng = np.random.default_rng(0)
        ok, jpg = cv2.imencode(".jpg", rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
        assert ok
        n = 5
        _BASE = KeyframeMsg(
            robot_id="r1",
            session_id="s1",
            seq=0,
            stamp=T0,
            T_odom_camera=np.eye(4),
            pose_source="rgb",
            keypoints=Keypoints(
                uv=(rng.random((n, 2)) * [W - 1, H - 1]).astype(np.float32),
                octave=np.zeros(n, np.int8),
                angle_deg=(rng.random(n) * 360).astype(np.float32),
                depth_m=rng.uniform(0.5, 4.0, n).astype(np.float32),
                descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
            ),
            rgb_jpeg=bytes(jpg.tobytes()),
            depth=PackedRaster(*wire.encode_depth(rng.uniform(0.5, 4.0, (H // 2, W // 2)))),
            intrinsics=Intrinsics(W, H, 50.0, 50.0, 31.5, 23.5, (0.0, 0.0, 0.0, 0.0, 0.0), 5000.0),
        )
    return _BASE


def keyframe(
    robot: str = "r1",
    session: str = "s1",
    seq: int = 0,
    stamp: float | None = None,
    pose_source: wire.PoseSource = "rgb",
) -> tuple[KeyframeMsg, bytes]:
    """A keyframe with this key (stamp ``T0 + seq`` unless given) and its wire bytes."""
    t = T0 + seq if stamp is None else stamp
    msg = replace(
        base_keyframe(),
        robot_id=robot,
        session_id=session,
        seq=seq,
        stamp=t,
        T_odom_camera=_pose(t - T0),
        pose_source=pose_source,
    )
    return msg, wire.encode(msg)


def _integrity(path: Path) -> str:
    with sqlite3.connect(path) as conn:
        return str(conn.execute("PRAGMA integrity_check").fetchone()[0])


def _user_version(path: Path) -> int:
    with sqlite3.connect(path) as conn:
        return int(conn.execute("PRAGMA user_version").fetchone()[0])


@pytest.fixture
def db(tmp_path: Path) -> str:
    return f"sqlite:///{tmp_path / 'map.db'}"


def test_satisfies_protocol(db: str) -> None:
    """SqliteKeyframeStore is usable where a KeyframeStore is expected; StoreError is a WardmapError."""
    with open_store(db) as st:
        proto: KeyframeStore = st
        assert proto.stats().keyframes == 0
    assert issubclass(StoreError, WardmapError)


def test_insert_and_duplicate(db: str, caplog: pytest.LogCaptureFixture) -> None:
    """A key is stored once; the same key again is "duplicate", and different bytes keep the first copy
    with a warning."""
    msg, data = keyframe(seq=3)
    with open_store(db) as st:
        assert st.insert(msg, data, 100.0) == "stored"
        with caplog.at_level(logging.WARNING, logger="wardmap.server.store"):
            assert st.insert(msg, data, 101.0) == "duplicate"
            assert not caplog.records
            other, other_data = keyframe(seq=3, stamp=T0 + 50.0)
            assert other_data != data
            assert st.insert(other, other_data, 102.0) == "duplicate"
        assert any("different bytes" in r.getMessage() for r in caplog.records)
        assert st.payload("r1", "s1", 3) == data
        assert st.payload("r1", "s1", 4) is None
        page = st.keyframes("r1")
        assert page.rows == [KeyframeRow("r1", "s1", 3, T0 + 3, 100.0, "rgb", len(data))]
        assert page.next_cursor is None
        [summary] = st.robots()
        assert (summary.keyframes, summary.sessions, summary.first_seen_s, summary.last_seen_s) == (
            1,
            1,
            100.0,
            100.0,
        )
        stats = st.stats()
        assert (stats.robots, stats.sessions, stats.keyframes, stats.payload_bytes) == (1, 1, 1, len(data))
        assert stats.schema_version == len(MIGRATIONS)


def test_bad_arguments(db: str) -> None:
    """Bad inputs raise StoreError naming the problem and store nothing."""
    msg, data = keyframe()
    with open_store(db) as st:
        with pytest.raises(StoreError, match="payload"):
            st.insert(msg, b"", 1.0)
        with pytest.raises(StoreError, match="received_s"):
            st.insert(msg, data, float("nan"))
        with pytest.raises(StoreError, match="limit"):
            st.keyframes("r1", limit=0)
        with pytest.raises(StoreError, match="cursor"):
            st.keyframes("r1", after=("s1", 99))
        with pytest.raises(StoreError, match="reason"):
            st.count_rejection("")
        assert st.stats().keyframes == 0


def test_restart_keeps_everything(db: str) -> None:
    """Close and reopen: keyframes, payloads, robots, sessions and rejection counts are all there."""
    stored = [keyframe(robot=r, session=s, seq=i) for r in ("r1", "r2") for s in ("a", "b") for i in range(5)]
    with open_store(db) as st:
        for i, (msg, data) in enumerate(stored):
            assert st.insert(msg, data, 10.0 + i) == "stored"
        st.count_rejection("seq")
        before = (st.robots(), st.keyframes("r1"), st.trajectory("r2"), st.rejections(), st.stats())
    with open_store(db) as st:
        after = (st.robots(), st.keyframes("r1"), st.trajectory("r2"), st.rejections(), st.stats())
        for msg, data in stored:
            assert st.payload(msg.robot_id, msg.session_id, msg.seq) == data
            assert st.insert(msg, data, 99.0) == "duplicate"
    assert before[0] == after[0] and before[1] == after[1] and before[3:] == after[3:]
    np.testing.assert_array_equal(before[2][0], after[2][0])
    np.testing.assert_array_equal(before[2][1], after[2][1])


def test_trajectory_order_and_values(db: str) -> None:
    """Keyframes inserted out of order come back sorted by stamp with their exact poses; a session
    filter and an unknown robot work."""
    rng = np.random.default_rng(1)
    seqs = rng.permutation(20)
    with open_store(db) as st:
        for seq in seqs:
            session = "a" if seq % 2 else "b"
            msg, data = keyframe(session=session, seq=int(seq), stamp=T0 + 0.5 * int(seq))
            st.insert(msg, data, 1.0)
        stamps, T = st.trajectory("r1")
        assert stamps.dtype == np.float64 and T.shape == (20, 4, 4) and T.dtype == np.float64
        np.testing.assert_array_equal(stamps, T0 + 0.5 * np.arange(20))
        for t, pose in zip(stamps, T, strict=True):
            np.testing.assert_array_equal(pose, _pose(t - T0))
        stamps_a, T_a = st.trajectory("r1", "a")
        np.testing.assert_array_equal(stamps_a, T0 + 0.5 * np.arange(1, 20, 2))
        np.testing.assert_array_equal(T_a, T[1::2])
        empty_stamps, empty_T = st.trajectory("nobody")
        assert empty_stamps.shape == (0,) and empty_T.shape == (0, 4, 4)


def test_pagination_covers_every_row_once(db: str) -> None:
    """Paging with next_cursor (limit 7, many equal stamps across sessions) yields every row exactly
    once in (stamp, session, seq) order; a stamp cursor starts after that time."""
    rng = np.random.default_rng(2)
    expected = []
    with open_store(db) as st:
        for session in ("a", "b", "c"):
            for seq in range(15):
                stamp = T0 + float(rng.integers(0, 10))  # many ties
                msg, data = keyframe(session=session, seq=seq, stamp=stamp)
                st.insert(msg, data, 1.0)
                expected.append((stamp, session, seq))
        st.insert(*keyframe(robot="r2", seq=0), 1.0)  # another robot never shows up
        expected.sort()
        got: list[tuple[float, str, int]] = []
        cursor = None
        pages = 0
        while True:
            page = st.keyframes("r1", after=cursor, limit=7)
            pages += 1
            got += [(r.stamp, r.session_id, r.seq) for r in page.rows]
            if page.next_cursor is None:
                break
            cursor = page.next_cursor
        assert got == expected
        assert pages == -(-len(expected) // 7)
        since = st.keyframes("r1", after=T0 + 4.0, limit=1000).rows
        assert [(r.stamp, r.session_id, r.seq) for r in since] == [e for e in expected if e[0] > T0 + 4.0]
        assert st.keyframes("nobody").rows == []


def test_rejection_counts(db: str) -> None:
    """count_rejection adds one per call per reason; rejections() returns them all; stats sums them."""
    with open_store(db) as st:
        assert st.rejections() == {}
        for reason in ("wire:stamp", "wire:stamp", "too_large", "wire:stamp"):
            st.count_rejection(reason)
        assert st.rejections() == {"too_large": 1, "wire:stamp": 3}
        assert st.stats().rejections == 4


def test_two_robots(db: str) -> None:
    """Robots are kept apart: per-robot counts, sessions, first/last seen, pages and trajectories."""
    with open_store(db) as st:
        for i in range(3):
            st.insert(*keyframe(robot="r1", session="s1", seq=i), 10.0 + i)
        for i in range(2):
            st.insert(*keyframe(robot="r2", session=f"s{i}", seq=0), 20.0 + i)
        assert st.robots() == [RobotSummary("r1", 3, 1, 10.0, 12.0), RobotSummary("r2", 2, 2, 20.0, 21.0)]
        assert {r.robot_id for r in st.keyframes("r2").rows} == {"r2"}
        assert len(st.trajectory("r1")[0]) == 3 and len(st.trajectory("r2")[0]) == 2
        assert st.payload("r2", "s1", 0) != st.payload("r1", "s1", 0)


def test_migration_from_empty_v0_file(tmp_path: Path) -> None:
    """A zero-byte file and an empty SQLite file at user_version 0 are migrated to the latest version
    in WAL mode and then accept inserts."""
    for name, make in (
        ("zero.db", lambda p: p.write_bytes(b"")),
        ("v0.db", lambda p: sqlite3.connect(p).close()),
    ):
        path = tmp_path / name
        make(path)
        with SqliteKeyframeStore.open(path) as st:
            assert st.insert(*keyframe(), 1.0) == "stored"
        assert _user_version(path) == len(MIGRATIONS)
        with sqlite3.connect(path) as conn:
            tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            assert {"robots", "sessions", "keyframes", "rejections"} <= tables
            assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
            indexes = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'index'")}
            assert "keyframes_robot_stamp" in indexes


def test_failed_migration_rolls_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A migration that fails half-way leaves the file at version 0 with no tables (one transaction)."""
    path = tmp_path / "map.db"
    broken = ((*MIGRATIONS[0], "CREATE TABLE robots (x)"),)  # the second CREATE of robots fails
    monkeypatch.setattr(store_mod, "STORE_DB", dataclasses.replace(store_mod.STORE_DB, migrations=broken))
    with pytest.raises(StoreError, match="cannot prepare"):
        SqliteKeyframeStore.open(path)
    assert _user_version(path) == 0
    with sqlite3.connect(path) as conn:
        assert conn.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()[0] == 0


def test_future_version_asks_to_upgrade(tmp_path: Path) -> None:
    """A store written by a newer wardmap (user_version above ours) is refused: "upgrade wardmap"."""
    path = tmp_path / "map.db"
    open_store(f"sqlite:///{path}").close()
    with sqlite3.connect(path) as conn:
        conn.execute(f"PRAGMA user_version = {len(MIGRATIONS) + 1}")
    with pytest.raises(StoreError, match="upgrade wardmap"):
        open_store(f"sqlite:///{path}")


def test_corrupt_file(tmp_path: Path) -> None:
    """A file of random bytes raises StoreError saying so and is left untouched."""
    path = tmp_path / "map.db"
    data = np.random.default_rng(7).integers(0, 256, 8192, dtype=np.uint8).tobytes()
    path.write_bytes(data)
    with pytest.raises(StoreError, match="not a wardmap keyframe store or it is corrupt"):
        open_store(f"sqlite:///{path}")
    assert path.read_bytes() == data


def test_foreign_sqlite_file(tmp_path: Path) -> None:
    """A valid SQLite file of some other program is refused, not migrated into."""
    path = tmp_path / "other.db"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE patients (name TEXT)")
    with pytest.raises(StoreError, match="not a wardmap keyframe store"):
        open_store(f"sqlite:///{path}")


def test_unwritable_path(tmp_path: Path) -> None:
    """A path under a regular file, or a path that is a directory, raises StoreError."""
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(StoreError, match="cannot create the store folder"):
        open_store(f"sqlite:///{blocker / 'sub' / 'map.db'}")
    (tmp_path / "dir.db").mkdir()
    with pytest.raises(StoreError, match="directory"):
        open_store(f"sqlite:///{tmp_path / 'dir.db'}")


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file permissions")
def test_read_only_folder(tmp_path: Path) -> None:
    """A folder without write permission raises StoreError (skipped as root)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(StoreError, match="cannot"):
            open_store(f"sqlite:///{folder / 'map.db'}")
    finally:
        folder.chmod(0o700)


@pytest.mark.parametrize(
    ("url", "match"),
    [
        ("postgresql://u:secret@host/db", "not available yet"),
        ("mysql://host/db", "unknown store URL"),
        ("map.db", "unknown store URL"),
        ("sqlite:///", "no file path"),
        ("sqlite:///:memory:", "plain file path"),
    ],
)
def test_bad_urls(url: str, match: str) -> None:
    """Unknown schemes, an empty path and in-memory databases raise StoreError (no password echoed)."""
    with pytest.raises(StoreError, match=match) as info:
        open_store(url)
    assert "secret" not in str(info.value)


def test_relative_url(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``sqlite:///x/map.db`` is relative to the working folder; the parent folder is created."""
    monkeypatch.chdir(tmp_path)
    open_store("sqlite:///x/map.db").close()
    assert (tmp_path / "x" / "map.db").is_file()


def test_closed_store_raises(db: str) -> None:
    """Every call on a closed store raises StoreError; close is idempotent."""
    st = open_store(db)
    st.close()
    st.close()
    with pytest.raises(StoreError, match="closed"):
        st.stats()
    with pytest.raises(StoreError, match="closed"):
        st.insert(*keyframe(), 1.0)


@pytest.mark.timeout(60)
def test_reader_thread_while_writer_inserts(db: str) -> None:
    """A writer thread inserts 500 keyframes while a reader thread pages, counts and reads
    trajectories; neither raises, counts only grow, and the final counts are exact."""
    n = 500
    msgs = [keyframe(session="s" + str(i % 3), seq=i) for i in range(n)]
    errors: list[BaseException] = []
    done = threading.Event()
    reading = threading.Event()  # the writer starts once the reader is in its loop
    seen: list[int] = []
    with open_store(db) as st:

        def write() -> None:
            try:
                if not reading.wait(timeout=30):
                    raise AssertionError("reader never started")
                for i, (msg, data) in enumerate(msgs):
                    if st.insert(msg, data, 1.0 + i) != "stored":
                        raise AssertionError(f"insert {i} not stored")
            except BaseException as exc:
                errors.append(exc)
            finally:
                done.set()

        def read() -> None:
            try:
                while not done.is_set() or not seen:
                    count = st.stats().keyframes
                    if seen and count < seen[-1]:
                        raise AssertionError("keyframe count went down")
                    seen.append(count)
                    reading.set()
                    stamps, T = st.trajectory("r1")
                    if len(stamps) != len(T) or np.any(np.diff(stamps) < 0):
                        raise AssertionError("trajectory inconsistent")
                    st.keyframes("r1", limit=50)
                    st.robots()
            except BaseException as exc:
                errors.append(exc)

        threads = [threading.Thread(target=write), threading.Thread(target=read)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=50)
        assert not any(t.is_alive() for t in threads)
        assert errors == []
        assert seen[0] == 0 and seen[-1] <= n
        stats = st.stats()
        assert (stats.keyframes, stats.sessions, stats.robots) == (n, 3, 1)
        [summary] = st.robots()
        assert (summary.keyframes, summary.first_seen_s, summary.last_seen_s) == (n, 1.0, float(n))
    assert _integrity(Path(db.removeprefix("sqlite:///"))) == "ok"


_CHILD = """
import sys
sys.path.insert(0, sys.argv[2])
from test_store import keyframe
from wardmap.server.store import open_store
with open_store("sqlite:///" + sys.argv[1]) as st:
    for seq in range(1_000_000):
        msg, data = keyframe(session="crash", seq=seq)
        assert st.insert(msg, data, 1.0 + seq) == "stored"
        sys.stdout.write(f"{seq}\\n")
        sys.stdout.flush()
"""


@pytest.mark.timeout(60)
def test_crash_safety_sigkill(tmp_path: Path) -> None:
    """A child inserting keyframes is SIGKILLed mid-stream; every insert it reported as committed is
    on disk with intact bytes, and integrity_check is ok.

    The child prints each seq after insert() returned. We kill it after 50 reports, then read every
    line it managed to write before dying. At most the one insert in flight may be there unreported.
    """
    path = tmp_path / "map.db"
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path), str(Path(__file__).parent)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    reported: list[int] = []
    try:
        while len(reported) < 50:
            line = proc.stdout.readline()
            if not line:
                pytest.fail(f"child exited early: {proc.wait()} {proc.stderr.read() if proc.stderr else ''}")
            reported.append(int(line))
        os.kill(proc.pid, signal.SIGKILL)
        reported += [int(ln) for ln in proc.stdout.read().split()]
    finally:
        proc.kill()
        proc.wait()
        proc.stdout.close()
        if proc.stderr is not None:
            proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert reported == list(range(len(reported)))

    assert _integrity(path) == "ok"
    with open_store(f"sqlite:///{path}") as st:
        rows = st.keyframes("r1", limit=1000).rows
        seqs = [r.seq for r in rows]
        assert seqs[: len(reported)] == reported
        assert len(seqs) - len(reported) in (0, 1)
        for seq in seqs:
            assert st.payload("r1", "crash", seq) == keyframe(session="crash", seq=seq)[1]
    assert _integrity(path) == "ok"
