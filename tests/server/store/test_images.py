"""Erasing stored keyframe images (``erase_images``, ``images_erased_s``; retention and erase
orders): the images go, everything else of the keyframe stays, on every backend."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pytest

from wardmap.server.retention import ImageRetention, RetentionConfig, parse_retention
from wardmap.server.store import MapStore, StoreError
from wardmap.shared import wire
from wardmap.shared.config import load_config
from wardmap.shared.errors import ConfigError

from .conftest import T0, Backend, keyframe


def _fill(store: MapStore) -> None:
    """r1: seq 0-5 (stamps T0+0..5, received T0+100+k); r2: seq 0-2 (received T0+200+k)."""
    for k in range(6):
        msg, payload = keyframe("r1", "s1", k)
        assert store.insert(msg, payload, T0 + 100 + k) == "stored"
    for k in range(3):
        msg, payload = keyframe("r2", "s1", k)
        assert store.insert(msg, payload, T0 + 200 + k) == "stored"


def _erased(store: MapStore, robot: str, n: int) -> list[bool]:
    return [store.images_erased_s(robot, "s1", k) is not None for k in range(n)]


def test_erase_by_capture_range_and_robot_keeps_poses_and_features(store: MapStore) -> None:
    """Stamps [T0+2, T0+4) of r1: two keyframes lose their images (a black JPEG of the same size,
    no thermal) and keep keypoints, depth and pose; others keep their bytes; a second call
    erases nothing more."""
    _fill(store)
    before = {k: store.payload("r1", "s1", k) for k in range(6)}
    trajectory = store.trajectory("r1")
    n = store.erase_images(now_s=T0 + 1000, stamp_from=T0 + 2, stamp_to=T0 + 4, robot_id="r1")
    assert n == 2
    assert _erased(store, "r1", 6) == [False, False, True, True, False, False]
    assert store.images_erased_s("r1", "s1", 2) == T0 + 1000
    assert _erased(store, "r2", 3) == [False] * 3
    for k in (0, 1, 4, 5):
        assert store.payload("r1", "s1", k) == before[k]
    original = wire.decode_keyframe(before[2] or b"")
    payload = store.payload("r1", "s1", 2)
    assert payload is not None
    stripped = wire.decode_keyframe(payload)
    image = cv2.imdecode(np.frombuffer(stripped.rgb_jpeg, np.uint8), cv2.IMREAD_COLOR)
    raw = cv2.imdecode(np.frombuffer(original.rgb_jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == raw.shape
    assert int(image.max()) <= 2 and stripped.thermal is None
    assert np.array_equal(stripped.keypoints.descriptors, original.keypoints.descriptors)
    assert np.array_equal(stripped.keypoints.uv, original.keypoints.uv)
    assert stripped.depth == original.depth
    assert np.array_equal(stripped.T_odom_camera, original.T_odom_camera)
    after = store.trajectory("r1")
    assert np.array_equal(after[0], trajectory[0]) and np.array_equal(after[1], trajectory[1])
    assert store.erase_images(now_s=T0 + 2000, stamp_from=T0 + 2, stamp_to=T0 + 4, robot_id="r1") == 0
    assert store.images_erased_s("r1", "s1", 2) == T0 + 1000
    assert store.images_erased_s("r9", "s1", 0) is None


def test_retention_erases_what_was_received_before_the_cutoff(store: MapStore) -> None:
    """Retention 150 s at T0+256: r1 (received T0+100..105) loses its images, r2 (T0+200..202) keeps them."""
    _fill(store)
    job = ImageRetention(store, retention_s=150.0, check_s=60.0)
    assert job.run_once(now_s=T0 + 256.0) == 6
    assert _erased(store, "r1", 6) == [True] * 6
    assert _erased(store, "r2", 3) == [False] * 3
    assert job.run_once(now_s=T0 + 352.5) == 3
    assert store.stats().keyframes == 9


def test_erase_needs_a_filter_and_sane_values(store: MapStore) -> None:
    with pytest.raises(StoreError, match="at least one filter"):
        store.erase_images(now_s=T0)
    with pytest.raises(StoreError, match="stamp_from"):
        store.erase_images(now_s=T0, stamp_from=float("nan"))


@pytest.mark.parametrize(("text", "seconds"), [("30d", 30 * 86400.0), ("12h", 43200.0), ("90m", 5400.0),
                                                ("3600s", 3600.0), ("none", None), ("0", None)])
def test_retention_durations(text: str, seconds: float | None) -> None:
    assert parse_retention(text) == seconds


@pytest.mark.parametrize("text", ["30", "30 days", "-1d", "0d", "1w"])
def test_bad_retention_is_rejected(tmp_path: Path, text: str) -> None:
    path = tmp_path / "server.toml"
    path.write_text(f'[store]\nimage_retention = "{text}"\n')
    with pytest.raises(ConfigError, match=r"store\.image_retention"):
        load_config(RetentionConfig, path, section="store")


def test_example_config_holds_the_defaults() -> None:
    path = Path(__file__).resolve().parents[3] / "deploy" / "server.toml"
    assert load_config(RetentionConfig, path, section="store") == RetentionConfig()


def test_erased_images_leave_no_bytes_in_the_sqlite_file(backend: Backend) -> None:
    """After erasing and a checkpoint, no piece of a stored JPEG's entropy-coded data is left
    anywhere in the database file (secure_delete zeroes what the old payloads occupied)."""
    if backend.name != "sqlite":
        pytest.skip("a file-level check of the SQLite backend")
    with backend.open() as store:
        _fill(store)
        msg, _ = keyframe("r1", "s1", 0)
        piece = msg.rgb_jpeg[-60:-20]  # scan data, not the tables every JPEG shares
        assert store.erase_images(now_s=T0 + 1000, robot_id="r1") == 6
        assert store.erase_images(now_s=T0 + 1000, robot_id="r2") == 3
    with sqlite3.connect(backend.path) as conn:
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    assert backend.path.read_bytes().count(piece) == 0
