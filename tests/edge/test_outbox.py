"""The durable keyframe outbox (``wardmap.edge.outbox``).

Each test opens a fresh SQLite file under ``tmp_path``. Payloads are deterministic bytes
derived from the key, so a reopened outbox can be checked item by item. The crash test
SIGKILLs a real child process that is putting items; it synchronises on the lines the
child writes after each committed put, never on sleeps.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import queue
import signal
import sqlite3
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from procs import sigkill_after

from wardmap.edge import outbox as outbox_mod
from wardmap.edge.outbox import (
    Outbox,
    OutboxError,
    OutboxFull,
    OutboxKey,
    new_session_id,
)
from wardmap.shared.errors import WardmapError

ROBOT = "r1"
SESSION = "s1"


def _payload(seq: int, size: int = 64) -> bytes:
    """Deterministic payload of ``size`` bytes for ``seq``."""
    block = hashlib.sha256(str(seq).encode()).digest()
    return (block * (size // len(block) + 1))[:size]


def _meta_version(conn: sqlite3.Connection) -> str:
    return str(conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0])


def _integrity(path: Path) -> str:
    with sqlite3.connect(path) as conn:
        return str(conn.execute("PRAGMA integrity_check").fetchone()[0])


def test_round_trip_in_order(tmp_path: Path) -> None:
    """Items of two sessions put out of seq order come back by session start, then seq; acks remove them."""
    with Outbox.open(tmp_path / "ob.db") as ob:
        for seq in (2, 0, 1):
            ob.put(ROBOT, "a", seq, 10.0 + seq, _payload(seq))
        ob.put(ROBOT, "b", 0, 20.0, _payload(100))
        items = ob.pending()
        assert [it.key for it in items] == [
            (ROBOT, "a", 0),
            (ROBOT, "a", 1),
            (ROBOT, "a", 2),
            (ROBOT, "b", 0),
        ]
        assert items[0].payload == _payload(0) and items[0].stamp == 10.0
        assert items[0].attempts == 0 and items[0].last_sent_s is None
        assert [it.key for it in ob.pending(limit=2)] == [it.key for it in items[:2]]
        assert len(ob) == 4
        stats = ob.stats()
        assert (stats.items, stats.bytes, stats.oldest_stamp, stats.max_attempts) == (4, 4 * 64, 10.0, 0)
        assert ob.ack(ROBOT, "a", 1)
        assert ob.ack_many([(ROBOT, "a", 0), (ROBOT, "b", 0)]) == 2
        assert [it.key for it in ob.pending()] == [(ROBOT, "a", 2)]
        assert ob.ack(ROBOT, "a", 2)
        assert ob.pending() == [] and len(ob) == 0
        assert ob.stats().oldest_stamp is None and ob.stats().bytes == 0


def test_ack_is_idempotent(tmp_path: Path) -> None:
    """Acking twice, or acking a key never put, returns False and changes nothing else."""
    with Outbox.open(tmp_path / "ob.db") as ob:
        ob.put(ROBOT, SESSION, 0, 1.0, b"x")
        ob.put(ROBOT, SESSION, 1, 2.0, b"y")
        assert ob.ack(ROBOT, SESSION, 0) is True
        assert ob.ack(ROBOT, SESSION, 0) is False
        assert ob.ack(ROBOT, "other", 0) is False
        assert ob.ack_many([(ROBOT, SESSION, 0), (ROBOT, SESSION, 1), (ROBOT, SESSION, 1)]) == 1
        assert ob.ack_many([]) == 0
        assert len(ob) == 0 and ob.stats().items == 0


def test_duplicate_put(tmp_path: Path) -> None:
    """Re-putting a key with the same stamp+payload is a no-op; a different payload or stamp is an error."""
    with Outbox.open(tmp_path / "ob.db") as ob:
        ob.put(ROBOT, SESSION, 0, 1.0, b"abc")
        ob.put(ROBOT, SESSION, 0, 1.0, bytearray(b"abc"))
        assert len(ob) == 1
        with pytest.raises(OutboxError, match="different"):
            ob.put(ROBOT, SESSION, 0, 1.0, b"abd")
        with pytest.raises(OutboxError, match="different"):
            ob.put(ROBOT, SESSION, 0, 1.5, b"abc")
        [item] = ob.pending()
        assert item.payload == b"abc" and item.stamp == 1.0


def test_bad_arguments(tmp_path: Path) -> None:
    """Malformed keys, stamps, payloads and limits raise OutboxError naming the argument."""
    with Outbox.open(tmp_path / "ob.db") as ob:
        with pytest.raises(OutboxError, match="robot_id"):
            ob.put("", SESSION, 0, 1.0, b"x")
        with pytest.raises(OutboxError, match="seq"):
            ob.put(ROBOT, SESSION, -1, 1.0, b"x")
        with pytest.raises(OutboxError, match="seq"):
            ob.put(ROBOT, SESSION, True, 1.0, b"x")
        with pytest.raises(OutboxError, match="stamp"):
            ob.put(ROBOT, SESSION, 0, float("nan"), b"x")
        with pytest.raises(OutboxError, match="payload"):
            not_bytes: Any = "text"  # the wrong type on purpose
            ob.put(ROBOT, SESSION, 0, 1.0, not_bytes)
        with pytest.raises(OutboxError, match="limit"):
            ob.pending(0)
        with pytest.raises(OutboxError, match="resend_after_s"):
            ob.pending(resend_after_s=-1.0)
        assert len(ob) == 0
    with pytest.raises(OutboxError, match="max_items"):
        Outbox.open(tmp_path / "ob2.db", max_items=0)


def test_full_raises_and_loses_nothing(tmp_path: Path) -> None:
    """At max_items or max_bytes a put raises OutboxFull, stores and evicts nothing; an ack makes room."""
    path = tmp_path / "ob.db"
    with Outbox.open(path, max_items=3, max_bytes=1000) as ob:
        for seq in range(3):
            ob.put(ROBOT, SESSION, seq, float(seq), _payload(seq, 100))
        with pytest.raises(OutboxFull, match="full"):
            ob.put(ROBOT, SESSION, 3, 3.0, _payload(3, 100))
        ob.put(ROBOT, SESSION, 2, 2.0, _payload(2, 100))  # an identical retry is still fine when full
        assert [it.seq for it in ob.pending()] == [0, 1, 2]
        assert ob.ack(ROBOT, SESSION, 0)
        ob.put(ROBOT, SESSION, 3, 3.0, _payload(3, 100))
        assert [it.payload for it in ob.pending()] == [_payload(s, 100) for s in (1, 2, 3)]
    with Outbox.open(path, max_items=100, max_bytes=500) as ob:  # bytes bound: 300 stored + 250 > 500
        with pytest.raises(OutboxFull):
            ob.put(ROBOT, SESSION, 4, 4.0, _payload(4, 250))
        with pytest.raises(OutboxError, match="exceeds the outbox capacity") as info:
            ob.put(ROBOT, SESSION, 5, 5.0, _payload(5, 501))
        assert not isinstance(info.value, OutboxFull)  # would never fit: not a retry-later condition
        assert len(ob) == 3 and ob.stats().bytes == 300
        assert isinstance(info.value, WardmapError)


def test_reopen_keeps_pending_and_attempts(tmp_path: Path) -> None:
    """Items, attempts and last_sent_s survive close + reopen; nothing acked comes back."""
    path = tmp_path / "sub" / "dir" / "ob.db"
    with Outbox.open(path) as ob:
        for seq in range(5):
            ob.put(ROBOT, SESSION, seq, float(seq), _payload(seq))
        ob.mark_sent([(ROBOT, SESSION, 0), (ROBOT, SESSION, 1)], now=50.0)
        ob.ack(ROBOT, SESSION, 1)
    with Outbox.open(path) as ob:
        items = ob.pending()
        assert [it.seq for it in items] == [0, 2, 3, 4]
        assert [it.payload for it in items] == [_payload(s) for s in (0, 2, 3, 4)]
        assert (items[0].attempts, items[0].last_sent_s) == (1, 50.0)
        assert len(ob) == 4 and ob.stats().max_attempts == 1
    assert _integrity(path) == "ok"


def test_sessions_restart_resends_old_keys(tmp_path: Path) -> None:
    """A restarted agent gets a new session; old unacked items keep their session/seq and come first.

    next_seq is persisted: it is not reused within a session even after all its items were acked,
    and a failed (full) put consumes no seq.
    """
    path = tmp_path / "ob.db"
    with Outbox.open(path, max_items=3) as ob:
        first = ob.start_session(ROBOT)
        assert first.next_seq == 0
        assert [first.put(float(i), _payload(i)) for i in range(3)] == [0, 1, 2]
        with pytest.raises(OutboxFull):
            first.put(3.0, _payload(3))
        assert first.next_seq == 3
        ob.ack(ROBOT, first.session_id, 0)
    with Outbox.open(path, max_items=10) as ob:
        second = ob.start_session(ROBOT)
        assert second.session_id != first.session_id
        assert second.put(9.0, b"new") == 0
        keys = [it.key for it in ob.pending()]
        assert keys == [
            (ROBOT, first.session_id, 1),
            (ROBOT, first.session_id, 2),
            (ROBOT, second.session_id, 0),
        ]
        ob.ack_many(keys[:2])
        resumed = ob.start_session(ROBOT, session_id=first.session_id)
        assert resumed.next_seq == 3  # all acked, still no reuse of 0..2
    ids = {new_session_id() for _ in range(100)}
    assert len(ids) == 100 and all(len(i.split("-")) == 2 for i in ids)


def test_resend_after_timeout(tmp_path: Path) -> None:
    """With resend_after_s, recently sent items are skipped and return once the timeout has passed."""
    with Outbox.open(tmp_path / "ob.db") as ob:
        for seq in range(3):
            ob.put(ROBOT, SESSION, seq, float(seq), _payload(seq))
        assert ob.mark_sent([(ROBOT, SESSION, 0), (ROBOT, SESSION, 1), (ROBOT, "gone", 9)], now=100.0) == 2
        assert [it.seq for it in ob.pending(resend_after_s=5.0, now=104.9)] == [2]
        assert [it.seq for it in ob.pending(now=104.9)] == [0, 1, 2]  # no timeout given: everything
        assert [it.seq for it in ob.pending(resend_after_s=5.0, now=105.0)] == [0, 1, 2]
        ob.mark_sent([it.key for it in ob.pending(resend_after_s=5.0, now=105.0)], now=105.0)
        assert ob.pending(resend_after_s=5.0, now=106.0) == []
        assert [it.attempts for it in ob.pending()] == [2, 2, 1]
        # the wall clock jumped back before the last send: the items count as due, not stuck
        assert [it.seq for it in ob.pending(resend_after_s=5.0, now=50.0)] == [0, 1, 2]
        assert ob.stats().max_attempts == 2


def test_thread_safety_writer_and_acker(tmp_path: Path) -> None:
    """A writer thread puts 2000 items, an acker thread acks them, the main thread sends: all acked."""
    n = 2000
    keys: queue.Queue[OutboxKey | None] = queue.Queue(maxsize=64)  # bounded; policy: block the writer
    errors: list[BaseException] = []
    acked: list[bool] = []

    with Outbox.open(tmp_path / "ob.db") as ob:

        def writer() -> None:
            try:
                for seq in range(n):
                    ob.put(ROBOT, SESSION, seq, float(seq), _payload(seq, 32))
                    keys.put((ROBOT, SESSION, seq))
            except BaseException as exc:
                errors.append(exc)
            finally:
                keys.put(None)

        def acker() -> None:
            try:
                while (key := keys.get()) is not None:
                    acked.append(ob.ack(*key))
            except BaseException as exc:
                errors.append(exc)

        threads = [threading.Thread(target=writer), threading.Thread(target=acker)]
        for t in threads:
            t.start()
        while threads[1].is_alive():
            ob.mark_sent([it.key for it in ob.pending(10)])
            assert 0 <= ob.stats().items <= n
        for t in threads:
            t.join()
        assert errors == []
        assert len(acked) == n and all(acked)
        assert ob.pending() == [] and len(ob) == 0 and ob.stats().bytes == 0


_CHILD = """
import hashlib, sys
from wardmap.edge.outbox import Outbox
def payload(seq):
    block = hashlib.sha256(str(seq).encode()).digest()
    return (block * 32)[:1000]
with Outbox.open(sys.argv[1]) as ob:
    ids = ob.start_session("r1", session_id="crash")
    for i in range(1_000_000):
        seq = ids.put(float(i), payload(i))
        sys.stdout.write(f"{seq}\\n")
        sys.stdout.flush()
"""


@pytest.mark.timeout(60)
def test_crash_safety_sigkill(tmp_path: Path) -> None:
    """A child putting items is SIGKILLed mid-stream; every put it reported as committed is on disk.

    The child prints each seq after put() returned. We kill it after 100 reports, then read
    every line it managed to write. The reopened outbox holds all reported items (plus at
    most the one in flight) with intact payloads, and integrity_check is ok.
    """
    path = tmp_path / "ob.db"
    reported, returncode = sigkill_after([sys.executable, "-c", _CHILD, str(path)], 100)
    assert returncode == -signal.SIGKILL
    assert reported == list(range(len(reported)))

    assert _integrity(path) == "ok"
    with Outbox.open(path) as ob:  # the dead child's lock is gone with it
        items = ob.pending(limit=1_000_000)
        seqs = [it.seq for it in items]
        assert seqs[: len(reported)] == reported
        assert len(seqs) - len(reported) in (0, 1)
        for it in items:
            assert it.payload == (hashlib.sha256(str(it.seq).encode()).digest() * 32)[:1000]
            assert it.stamp == float(it.seq) and it.session_id == "crash"
        assert ob.next_seq(ROBOT, "crash") == len(seqs)
    assert _integrity(path) == "ok"


def test_second_open_is_refused(tmp_path: Path) -> None:
    """One owner per file: a second open while the first is open raises; after close it works."""
    path = tmp_path / "ob.db"
    with Outbox.open(path), pytest.raises(OutboxError, match="already open"):
        Outbox.open(path)
    with Outbox.open(path) as ob:
        ob.close()
        ob.close()  # idempotent
        with pytest.raises(OutboxError, match="closed"):
            ob.pending()
        with pytest.raises(OutboxError, match="closed"):
            len(ob)


def test_corrupt_file(tmp_path: Path) -> None:
    """A file of random bytes raises OutboxError saying so, is left untouched, and releases the lock."""
    path = tmp_path / "ob.db"
    data = np.random.default_rng(7).integers(0, 256, 8192, dtype=np.uint8).tobytes()
    path.write_bytes(data)
    for _ in range(2):  # the second attempt must not see a leftover lock
        with pytest.raises(OutboxError, match="not a wardmap outbox database or it is corrupt"):
            Outbox.open(path)
    assert path.read_bytes() == data


def test_foreign_sqlite_file(tmp_path: Path) -> None:
    """A valid SQLite file of some other program is refused, not migrated into."""
    path = tmp_path / "other.db"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE patients (name TEXT)")
    with pytest.raises(OutboxError, match="not a wardmap outbox"):
        Outbox.open(path)


def test_unwritable_path(tmp_path: Path) -> None:
    """A path under a regular file, or a path that is a directory, raises OutboxError."""
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(OutboxError, match="cannot create the outbox folder"):
        Outbox.open(blocker / "sub" / "ob.db")
    (tmp_path / "dir.db").mkdir()
    with pytest.raises(OutboxError, match="directory"):
        Outbox.open(tmp_path / "dir.db")


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file permissions")
def test_read_only_folder(tmp_path: Path) -> None:
    """A folder without write permission raises OutboxError (skipped as root)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(OutboxError, match="cannot"):
            Outbox.open(folder / "ob.db")
    finally:
        folder.chmod(0o700)


def test_migrations_from_version_zero(tmp_path: Path) -> None:
    """An empty SQLite file (user_version 0) is migrated to the latest schema, WAL + FULL, meta filled."""
    path = tmp_path / "ob.db"
    sqlite3.connect(path).close()
    path.touch()
    with Outbox.open(path) as ob:
        ob.put(ROBOT, SESSION, 0, 1.0, b"x")
    with sqlite3.connect(path) as conn:
        latest = len(outbox_mod.MIGRATIONS)
        assert conn.execute("PRAGMA user_version").fetchone()[0] == latest
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert _meta_version(conn) == str(latest)
        assert conn.execute("SELECT COUNT(*) FROM outbox").fetchone()[0] == 1


def test_migration_upgrade_keeps_data_and_failure_rolls_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A v1 file opened by a build with a v2 migration is upgraded with its items; a failing migration
    raises OutboxError and leaves the file at v1, items intact."""
    path = tmp_path / "ob.db"
    with Outbox.open(path) as ob:
        ob.put(ROBOT, SESSION, 0, 1.0, b"keep")
    v1 = outbox_mod.MIGRATIONS
    broken = (*v1, ("ALTER TABLE outbox ADD COLUMN broken",), ("nonsense",))
    monkeypatch.setattr(outbox_mod, "OUTBOX_DB", dataclasses.replace(outbox_mod.OUTBOX_DB, migrations=broken))
    with pytest.raises(OutboxError, match="cannot prepare"):
        Outbox.open(path)
    with sqlite3.connect(path) as conn:
        assert conn.execute("PRAGMA user_version").fetchone()[0] == len(v1)
        assert "broken" not in [r[1] for r in conn.execute("PRAGMA table_info(outbox)")]
    v2 = (*v1, ("ALTER TABLE outbox ADD COLUMN note TEXT",))
    monkeypatch.setattr(outbox_mod, "OUTBOX_DB", dataclasses.replace(outbox_mod.OUTBOX_DB, migrations=v2))
    with Outbox.open(path) as ob:
        assert [it.payload for it in ob.pending()] == [b"keep"]
    with sqlite3.connect(path) as conn:
        assert conn.execute("PRAGMA user_version").fetchone()[0] == len(v1) + 1
        assert _meta_version(conn) == str(len(v1) + 1)


def test_future_version_asks_to_upgrade(tmp_path: Path) -> None:
    """A file whose user_version is above the known migrations raises OutboxError telling to upgrade."""
    path = tmp_path / "ob.db"
    with Outbox.open(path) as ob:
        ob.put(ROBOT, SESSION, 0, 1.0, b"x")
    with sqlite3.connect(path) as conn:
        conn.execute(f"PRAGMA user_version = {len(outbox_mod.MIGRATIONS) + 5}")
    with pytest.raises(OutboxError, match="upgrade wardmap"):
        Outbox.open(path)


def test_vacuum_keeps_items(tmp_path: Path) -> None:
    """vacuum() after acking most items keeps the rest and their order."""
    with Outbox.open(tmp_path / "ob.db") as ob:
        for seq in range(50):
            ob.put(ROBOT, SESSION, seq, float(seq), _payload(seq, 4096))
        ob.ack_many([(ROBOT, SESSION, s) for s in range(45)])
        ob.vacuum()
        assert [it.seq for it in ob.pending()] == list(range(45, 50))
        assert len(ob) == 5
