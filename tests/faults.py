"""Storage-fault helpers shared by tests: damage an SQLite index page, repair a damaged file the
way ``wardmap.server.store.REPAIR_HINT`` tells an operator (``.dump`` into a new file), small
valid keyframes.

Only for closed files: nothing else may have the database open while these run.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
from dataclasses import replace
from pathlib import Path

import factories
import numpy as np

from wardmap.shared import wire
from wardmap.shared.se3 import make_transform

W, H = 64, 48
T0 = 1_714_557_600.0  # 2024-05-01 10:00 UTC


def small_keyframes(robot: str, n: int, *, session: str = "s1", seed: int = 0) -> list[bytes]:
    """``n`` valid 64x48 keyframes of ``robot`` (seq 0..n-1, stamps T0 + seq), encoded."""
    base = factories.keyframe(np.random.default_rng(seed), robot_id=robot, session_id=session)
    return [
        wire.encode(replace(base, seq=i, stamp=T0 + i, T_odom_camera=make_transform(np.eye(3), [i, 0, 0])))
        for i in range(n)
    ]


def garble_index_page(db: Path, index: str = "keyframes_robot_stamp", seed: int = 0) -> int:
    """Overwrite the second half of ``index``'s root page (where its cells live) with seeded
    random bytes, after checkpointing the WAL into the file; returns the page number. Every
    statement that walks that index then fails with "database disk image is malformed"."""
    with contextlib.closing(sqlite3.connect(db)) as con:
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        row = con.execute("SELECT rootpage FROM sqlite_master WHERE type = 'index' AND name = ?", (index,))
        root = int(row.fetchone()[0])
        page_size = int(con.execute("PRAGMA page_size").fetchone()[0])
    noise = np.random.default_rng(seed).integers(0, 256, page_size // 2, dtype=np.uint8).tobytes()
    with db.open("r+b") as f:
        f.seek((root - 1) * page_size + page_size // 2)
        f.write(noise)
    return root


def repair_by_dump(db: Path) -> None:
    """Rebuild ``db`` from a dump of its tables (indexes are rebuilt from the rows), keep its
    ``application_id`` and ``user_version``, check it and move it in place: the ``.dump`` route
    of ``REPAIR_HINT``, done with Python's ``iterdump`` so no sqlite3 CLI is needed."""
    new = db.with_name(db.name + ".repaired")
    new.unlink(missing_ok=True)
    with contextlib.closing(sqlite3.connect(db)) as old:
        app_id = int(old.execute("PRAGMA application_id").fetchone()[0])
        version = int(old.execute("PRAGMA user_version").fetchone()[0])
        script = "\n".join(old.iterdump())
    with contextlib.closing(sqlite3.connect(new, isolation_level=None)) as fresh:
        fresh.executescript(script)
        fresh.execute(f"PRAGMA application_id = {app_id}")
        fresh.execute(f"PRAGMA user_version = {version}")
        check = fresh.execute("PRAGMA integrity_check").fetchall()
    if check != [("ok",)]:
        raise AssertionError(f"repaired file fails integrity_check: {check}")
    os.replace(new, db)
    for suffix in ("-wal", "-shm"):
        db.with_name(db.name + suffix).unlink(missing_ok=True)
