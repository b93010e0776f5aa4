"""Protocol tests of the store's keyframes (:class:`~wardmap.server.store.KeyframeStore`), run
against every backend (``conftest.BACKENDS``).

The thread test synchronises on events, never on sleeps.
"""

from __future__ import annotations

import logging
import threading

import numpy as np
import pytest

from wardmap.server.store import KeyframeRow, KeyframeStore, RobotSummary, StoreError
from wardmap.shared.errors import WardmapError

from .conftest import T0, Backend, keyframe, pose_at


def test_satisfies_protocol(backend: Backend) -> None:
    """What open_store returns is usable where a KeyframeStore is expected; StoreError is a WardmapError."""
    with backend.open() as st:
        proto: KeyframeStore = st
        assert proto.stats().keyframes == 0
    assert issubclass(StoreError, WardmapError)


def test_insert_and_duplicate(backend: Backend, caplog: pytest.LogCaptureFixture) -> None:
    """A key is stored once; the same key again is "duplicate", and different bytes keep the first copy
    with a warning."""
    msg, data = keyframe(seq=3)
    with backend.open() as st:
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
        assert stats.schema_version > 0


def test_bad_arguments(backend: Backend) -> None:
    """Bad inputs raise StoreError naming the problem and store nothing."""
    msg, data = keyframe()
    with backend.open() as st:
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


def test_restart_keeps_everything(backend: Backend) -> None:
    """Close and reopen: keyframes, payloads, robots, sessions and rejection counts are all there."""
    stored = [keyframe(robot=r, session=s, seq=i) for r in ("r1", "r2") for s in ("a", "b") for i in range(5)]
    with backend.open() as st:
        for i, (msg, data) in enumerate(stored):
            assert st.insert(msg, data, 10.0 + i) == "stored"
        st.count_rejection("seq")
        before = (st.robots(), st.keyframes("r1"), st.trajectory("r2"), st.rejections(), st.stats())
    with backend.open() as st:
        after = (st.robots(), st.keyframes("r1"), st.trajectory("r2"), st.rejections(), st.stats())
        for msg, data in stored:
            assert st.payload(msg.robot_id, msg.session_id, msg.seq) == data
            assert st.insert(msg, data, 99.0) == "duplicate"
    assert before[0] == after[0] and before[1] == after[1] and before[3:] == after[3:]
    np.testing.assert_array_equal(before[2][0], after[2][0])
    np.testing.assert_array_equal(before[2][1], after[2][1])


def test_trajectory_order_and_values(backend: Backend) -> None:
    """Keyframes inserted out of order come back sorted by stamp with their exact poses; a session
    filter and an unknown robot work."""
    rng = np.random.default_rng(1)
    seqs = rng.permutation(20)
    with backend.open() as st:
        for seq in seqs:
            session = "a" if seq % 2 else "b"
            msg, data = keyframe(session=session, seq=int(seq), stamp=T0 + 0.5 * int(seq))
            st.insert(msg, data, 1.0)
        stamps, T = st.trajectory("r1")
        assert stamps.dtype == np.float64 and T.shape == (20, 4, 4) and T.dtype == np.float64
        np.testing.assert_array_equal(stamps, T0 + 0.5 * np.arange(20))
        for t, pose in zip(stamps, T, strict=True):
            np.testing.assert_array_equal(pose, pose_at(t))
        stamps_a, T_a = st.trajectory("r1", "a")
        np.testing.assert_array_equal(stamps_a, T0 + 0.5 * np.arange(1, 20, 2))
        np.testing.assert_array_equal(T_a, T[1::2])
        empty_stamps, empty_T = st.trajectory("nobody")
        assert empty_stamps.shape == (0,) and empty_T.shape == (0, 4, 4)


def test_pagination_covers_every_row_once(backend: Backend) -> None:
    """Paging with next_cursor (limit 7, many equal stamps across sessions) yields every row exactly
    once in (stamp, session, seq) order; a stamp cursor starts after that time."""
    rng = np.random.default_rng(2)
    expected = []
    with backend.open() as st:
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


def test_rejection_counts(backend: Backend) -> None:
    """count_rejection adds one per call per reason; rejections() returns them all; stats sums them."""
    with backend.open() as st:
        assert st.rejections() == {}
        for reason in ("wire:stamp", "wire:stamp", "too_large", "wire:stamp"):
            st.count_rejection(reason)
        assert st.rejections() == {"too_large": 1, "wire:stamp": 3}
        assert st.stats().rejections == 4


def test_two_robots(backend: Backend) -> None:
    """Robots are kept apart: per-robot counts, sessions, first/last seen, pages and trajectories."""
    with backend.open() as st:
        for i in range(3):
            st.insert(*keyframe(robot="r1", session="s1", seq=i), 10.0 + i)
        for i in range(2):
            st.insert(*keyframe(robot="r2", session=f"s{i}", seq=0), 20.0 + i)
        assert st.robots() == [RobotSummary("r1", 3, 1, 10.0, 12.0), RobotSummary("r2", 2, 2, 20.0, 21.0)]
        assert {r.robot_id for r in st.keyframes("r2").rows} == {"r2"}
        assert len(st.trajectory("r1")[0]) == 3 and len(st.trajectory("r2")[0]) == 2
        assert st.payload("r2", "s1", 0) != st.payload("r1", "s1", 0)


def test_closed_store_raises(backend: Backend) -> None:
    """Every call on a closed store raises StoreError; close is idempotent."""
    st = backend.open()
    st.close()
    st.close()
    with pytest.raises(StoreError, match="closed"):
        st.stats()
    with pytest.raises(StoreError, match="closed"):
        st.insert(*keyframe(), 1.0)


@pytest.mark.timeout(60)
@pytest.mark.timeout(60)
def test_reader_thread_while_writer_inserts(backend: Backend) -> None:
    """A writer thread inserts 500 keyframes while a reader thread pages, counts and reads
    trajectories; neither raises, counts only grow, and the final counts are exact."""
    n = 500
    msgs = [keyframe(session="s" + str(i % 3), seq=i) for i in range(n)]
    errors: list[BaseException] = []
    done = threading.Event()
    reading = threading.Event()  # the writer starts once the reader is in its loop
    seen: list[int] = []
    with backend.open() as st:

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
    assert backend.integrity_ok()
