"""``wardmap images erase`` as a process: an erase order for a time range of capture stamps,
optionally of one robot, on a real store; bad input is one line and exit code 1."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import factories
import numpy as np
import pytest
from procs import one_line_error, wardmap

from wardmap.server.store import open_store
from wardmap.shared import wire

T0 = 1_764_151_200.0  # 2025-11-26T10:00:00Z


@pytest.fixture
def db(tmp_path: Path) -> str:
    """r1 and r2, keyframes every 10 minutes from 10:00 to 11:50 UTC (12 each)."""
    url = f"sqlite:///{tmp_path / 'map.db'}"
    base = factories.keyframe(np.random.default_rng(0))
    with open_store(url) as store:
        for robot in ("r1", "r2"):
            for k in range(12):
                msg = replace(base, robot_id=robot, seq=k, stamp=T0 + 600 * k)
                assert store.insert(msg, wire.encode(msg), T0 + 600 * k + 1) == "stored"
    return url


def _erased(url: str, robot: str) -> list[int]:
    with open_store(url) as store:
        return [k for k in range(12) if store.images_erased_s(robot, "s1", k) is not None]


def test_erase_a_range_of_one_robot(db: str) -> None:
    """10:30 (included) to 11:00 (excluded) of r1, given with a +01:00 zone: seq 3-5 only."""
    p = wardmap("images", "erase", "--db", db, "--from", "2025-11-26T11:30:00+01:00",
                "--to", "2025-11-26T11:00:00Z", "--robot", "r1")
    assert p.returncode == 0, p.stderr
    assert "erased the images of 3 keyframes" in p.stdout
    assert _erased(db, "r1") == [3, 4, 5] and _erased(db, "r2") == []
    p = wardmap("images", "erase", "--db", db, "--from", "2025-11-26T00:00:00Z",
                "--to", "2025-11-27T00:00:00Z")
    assert p.returncode == 0 and "erased the images of 21 keyframes" in p.stdout, p.stderr
    assert _erased(db, "r1") == list(range(12)) and _erased(db, "r2") == list(range(12))


@pytest.mark.parametrize(
    ("start", "end", "needle"),
    [
        ("yesterday", "2025-11-26T11:00:00Z", "bad --from 'yesterday'"),
        ("2025-11-26T10:00:00", "2025-11-26T11:00:00Z", "give a time zone"),
        ("2025-11-26T11:00:00Z", "2025-11-26T10:00:00Z", "must be before --to"),
    ],
)
def test_bad_input_is_one_line(db: str, start: str, end: str, needle: str) -> None:
    one_line_error(wardmap("images", "erase", "--db", db, "--from", start, "--to", end), needle, "images")
    assert _erased(db, "r1") == []


def test_a_missing_store_is_one_line(tmp_path: Path) -> None:
    missing = tmp_path / "nope.db"
    one_line_error(wardmap("images", "erase", "--db", f"sqlite:///{missing}",
                           "--from", "2025-11-26T10:00:00Z", "--to", "2025-11-26T11:00:00Z"),
                   "no store at", "images")
    assert not missing.exists()
