"""The keyframe store under storage faults: a full file (``max_pages`` cap), a write lock held
past the busy timeout by another connection, a corrupted index page. Each failure must come out
as the right :class:`StoreError` subclass (unavailable: retry later; damaged: repair), nothing
half-stored, and :meth:`SqliteKeyframeStore.writable` must say so and recover when the fault is
gone. Synchronisation is on returned calls only (no threads, no sleeps).
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import time
from pathlib import Path

import pytest
from faults import garble_index_page, repair_by_dump, small_keyframes

from wardmap.server.store import (
    REPAIR_HINT,
    StoreDamagedError,
    StoreError,
    StoreOptions,
    StoreUnavailableError,
    classify_sqlite_error,
    open_store,
)
from wardmap.shared import wire


def _msgs(robot: str, n: int, session: str = "s1") -> list[tuple[wire.KeyframeMsg, bytes]]:
    return [(wire.decode_keyframe(p), p) for p in small_keyframes(robot, n, session=session)]


def _rows(db: Path) -> int:
    with contextlib.closing(sqlite3.connect(db)) as con:
        return int(con.execute("SELECT COUNT(*) FROM keyframes").fetchone()[0])


def test_full_page_cap_is_unavailable_and_stays_not_ready_until_a_keyframe_fits(tmp_path: Path) -> None:
    """With ``max_pages`` just above the empty file, inserts succeed until one no longer fits:
    it raises StoreUnavailableError ("full") and stores nothing. A small rejection count still
    fits, yet writable() stays False (the probe is rolled back, so only an insert can show a
    keyframe fits). Reopened without the cap, the same insert succeeds and writable() is True."""
    db = tmp_path / "map.db"
    open_store(f"sqlite:///{db}").close()
    with contextlib.closing(sqlite3.connect(db)) as con:
        empty_pages = int(con.execute("PRAGMA page_count").fetchone()[0])
    msgs = _msgs("r1", 200)
    with open_store(f"sqlite:///{db}?max_pages={empty_pages + 6}") as st:
        assert st.options.max_pages == empty_pages + 6
        assert st.writable() == (True, "ok")
        stored = 0
        with pytest.raises(StoreUnavailableError, match="full") as info:
            for msg, payload in msgs:
                st.insert(msg, payload, 1.0)
                stored += 1
        assert not isinstance(info.value, StoreDamagedError)
        assert 0 < stored < len(msgs)
        assert _rows(db) == stored
        ok, why = st.writable()
        assert not ok and "full" in why, why
        with contextlib.suppress(StoreUnavailableError):  # it may not fit either; readiness is the point
            st.count_rejection("wire: payload", 2)
        ok, why = st.writable()
        assert not ok and "full" in why, why
    with open_store(f"sqlite:///{db}") as st:
        msg, payload = msgs[stored]
        assert st.insert(msg, payload, 2.0) == "stored"
        assert st.writable() == (True, "ok")
    assert _rows(db) == stored + 1


def test_write_lock_past_busy_timeout_is_unavailable_and_clears_when_released(tmp_path: Path) -> None:
    """Another connection holds ``BEGIN EXCLUSIVE``: an insert waits ``busy_timeout_s`` (0.2 s
    here) and raises StoreUnavailableError ("locked"); reads still work (WAL); writable() is
    False. Once the lock is released the probe passes (a lock failure needs no new write to
    clear) and the insert succeeds."""
    db = tmp_path / "map.db"
    with open_store(f"sqlite:///{db}?busy_timeout_s=0.2") as st:
        (msg, payload), = _msgs("r1", 1)
        with contextlib.closing(sqlite3.connect(db, isolation_level=None)) as holder:
            holder.execute("BEGIN EXCLUSIVE")
            t0 = time.monotonic()
            with pytest.raises(StoreUnavailableError, match="locked"):
                st.insert(msg, payload, 1.0)
            assert time.monotonic() - t0 >= 0.15
            assert st.robots() == []
            ok, why = st.writable()
            assert not ok and "locked" in why, why
            holder.execute("ROLLBACK")
        assert st.writable() == (True, "ok")
        assert st.insert(msg, payload, 1.0) == "stored"


def test_corrupt_index_page_is_damaged_logged_once_and_repairable(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An index page of ``keyframes_robot_stamp`` is overwritten with noise. The store still
    opens; an insert and the reads that walk the index raise StoreDamagedError whose message
    says how to repair; the damage is logged once, with the repair hint, however often it is
    hit; writable() reports it. After the ``.dump`` repair every old row is back and inserts work."""
    db = tmp_path / "map.db"
    old = _msgs("r1", 5)
    with open_store(f"sqlite:///{db}") as st:
        for msg, payload in old:
            st.insert(msg, payload, 1.0)
    garble_index_page(db)
    (new_msg, new_payload), = _msgs("r2", 1)
    with open_store(f"sqlite:///{db}") as st, caplog.at_level(logging.ERROR, logger="wardmap.server.store"):
        assert st.writable() == (True, "ok")  # nothing has walked the damaged index yet
        for _ in range(3):
            with pytest.raises(StoreDamagedError, match="damaged") as info:
                st.insert(new_msg, new_payload, 2.0)
            assert ".recover" in str(info.value) and "backup" in str(info.value)
        with pytest.raises(StoreDamagedError):
            st.keyframes("r1")
        ok, why = st.writable()
        assert not ok and why.startswith("damaged:") and "malformed" in why, why
    logged = [r for r in caplog.records if "damaged" in r.getMessage()]
    assert len(logged) == 1
    assert REPAIR_HINT in logged[0].getMessage()
    repair_by_dump(db)
    with open_store(f"sqlite:///{db}") as st:
        assert [r.seq for r in st.keyframes("r1").rows] == [0, 1, 2, 3, 4]
        assert st.insert(new_msg, new_payload, 3.0) == "stored"
        assert st.writable() == (True, "ok")


def test_classify_sqlite_error_by_code_and_by_message() -> None:
    """Real SQLite errors carry their code (full, locked, corrupt are mapped by it); errors built
    without one fall back on SQLite's fixed messages; anything else is a plain StoreError."""
    with contextlib.closing(sqlite3.connect(":memory:")) as con, pytest.raises(sqlite3.Error) as syntax:
        con.execute("SELEC 1")
    assert classify_sqlite_error(syntax.value) is StoreError
    unavailable = ["database or disk is full", "database is locked", "disk I/O error"]
    for text in unavailable:
        assert classify_sqlite_error(sqlite3.OperationalError(text)) is StoreUnavailableError, text
    for text in ["database disk image is malformed", "file is not a database"]:
        assert classify_sqlite_error(sqlite3.DatabaseError(text)) is StoreDamagedError, text
    assert classify_sqlite_error(sqlite3.IntegrityError("UNIQUE constraint failed")) is StoreError
    assert issubclass(StoreUnavailableError, StoreError) and issubclass(StoreDamagedError, StoreError)


@pytest.mark.parametrize(
    ("query", "match"),
    [
        ("busy=2", "unknown store option"),
        ("busy_timeout_s=soon", "must be a number"),
        ("busy_timeout_s=0", r"\(0, 600\]"),
        ("busy_timeout_s=nan", r"\(0, 600\]"),
        ("max_pages=0", "max_pages"),
        ("max_pages=1.5", "must be a number"),
        ("max_pages", "must be a number"),
    ],
)
def test_bad_store_options_name_the_option(tmp_path: Path, query: str, match: str) -> None:
    """A bad or unknown URL option raises StoreError naming it; nothing is created."""
    with pytest.raises(StoreError, match=match):
        open_store(f"sqlite:///{tmp_path / 'map.db'}?{query}")
    assert not (tmp_path / "map.db").exists()


def test_store_options_from_url(tmp_path: Path) -> None:
    """``?busy_timeout_s=..&max_pages=..`` reach the store; no query means the defaults."""
    with open_store(f"sqlite:///{tmp_path / 'a.db'}?busy_timeout_s=2.5&max_pages=100000") as st:
        assert st.options == StoreOptions(busy_timeout_s=2.5, max_pages=100000)
    with open_store(f"sqlite:///{tmp_path / 'b.db'}") as st:
        assert st.options == StoreOptions()


def test_count_rejection_adds_n_at_once(tmp_path: Path) -> None:
    """count_rejection(reason, n) adds n in one transaction; n < 1 is refused."""
    with open_store(f"sqlite:///{tmp_path / 'map.db'}") as st:
        st.count_rejection("wire: depth", 3)
        st.count_rejection("wire: depth")
        assert st.rejections() == {"wire: depth": 4}
        with pytest.raises(StoreError, match="n must be"):
            st.count_rejection("wire: depth", 0)
