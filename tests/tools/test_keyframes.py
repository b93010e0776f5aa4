"""Offline keyframe messages (tools/keyframes.py) on a few frames of a simulated run and of TUM."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from wardmap.shared.dataset import DatasetReader
from wardmap.shared.errors import DatasetError, WardmapError
from wardmap.shared.wire import encode
from wardmap.sim.runner import generate
from wardmap.tools.keyframes import (
    auto_labels,
    cache_keyframes,
    dataset_keyframes,
    folder_lock,
    groundtruth_at,
    read_keyframes,
)

TUM = Path(__file__).resolve().parents[3] / "shared" / "data" / "tum_fr1_rpy_s3_first100"
FRAMES = 16


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """hospital_loop, seed 0, the first 16 frames (the robot accelerates along the south corridor)."""
    out = tmp_path_factory.mktemp("sim") / "hospital_loop_s0"
    generate("hospital_loop", 0, out, frames=FRAMES)
    return out


def test_messages_of_a_simulated_run(sim: Path) -> None:
    """One message per keyframe, seq 0, 1, ... in stamp order, with the given ids, odometry and
    intrinsics; the first frame is a keyframe; a simulated data set gets oracle labels."""
    reader = DatasetReader(sim)
    assert auto_labels(reader) == "oracle"
    msgs = list(dataset_keyframes(sim, robot_id="r0", session_id="day-1"))
    assert len(msgs) >= 2
    assert [m.seq for m in msgs] == list(range(len(msgs)))
    assert msgs[0].stamp == pytest.approx(float(reader.stamps[0]))
    assert np.all(np.diff([m.stamp for m in msgs]) > 0)
    for m in msgs:
        assert (m.robot_id, m.session_id) == ("r0", "day-1")
        assert m.T_odom_base is not None and m.intrinsics is not None and m.T_map_odom is None
        assert len(m.keypoints) > 100
    assert msgs[0].thermal is not None  # thermal on keyframe 0 of every 4 (AgentConfig default)


def test_a_later_start_is_a_fresh_session(sim: Path) -> None:
    """Frames [8, 16): the tracker starts at frame 8, seq restarts at 0, stamps are from 8 on."""
    reader = DatasetReader(sim)
    msgs = list(dataset_keyframes(sim, robot_id="r0", session_id="b", start=8, stop=FRAMES))
    assert msgs and msgs[0].seq == 0
    assert msgs[0].stamp == pytest.approx(float(reader.stamps[8]))
    with pytest.raises(WardmapError, match="frame range"):
        next(dataset_keyframes(sim, robot_id="r0", session_id="b", start=10, stop=4))
    with pytest.raises(WardmapError, match="frame range"):
        next(dataset_keyframes(sim, robot_id="r0", session_id="b", stop=FRAMES + 1))


def test_cache_is_byte_identical_and_reused(sim: Path, tmp_path: Path) -> None:
    """The cached files are ``wire.encode`` of the messages a second, independent run yields
    (tracking and encoding are deterministic); truth is the ground truth at each stamp; an
    equal request reuses the folder, another one rebuilds it."""
    folder = tmp_path / "kf"
    cache = cache_keyframes(sim, folder, robot_id="r0", session_id="s")
    fresh = list(dataset_keyframes(sim, robot_id="r0", session_id="s"))
    assert len(cache) == len(fresh)
    for msg in fresh:
        assert cache.payload(msg.seq) == encode(msg)
    reader = DatasetReader(sim)
    for T, want in zip(cache.truth, groundtruth_at(reader, [m.stamp for m in fresh]), strict=True):
        assert T is not None and want is not None
        np.testing.assert_allclose(T, want, atol=1e-8)
    decoded = cache.message(0)
    np.testing.assert_allclose(decoded.T_odom_camera, fresh[0].T_odom_camera, atol=1e-12)
    mtime = cache.path(0).stat().st_mtime_ns
    again = cache_keyframes(sim, folder, robot_id="r0", session_id="s")
    assert again.path(0).stat().st_mtime_ns == mtime and len(again) == len(cache)
    other = cache_keyframes(sim, folder, robot_id="r0", session_id="s", start=8)
    assert other.params["start"] == 8 and other.stamps[0] == pytest.approx(float(reader.stamps[8]))
    assert len(list(folder.glob("*.msgpack"))) == len(other)
    assert [m.seq for m in other.messages()] == list(range(len(other)))


def test_folder_lock_makes_a_second_user_wait(tmp_path: Path) -> None:
    """While one holder has ``<folder>.lock``, another asking for it waits until it is released."""
    folder = tmp_path / "cache"
    got = threading.Event()

    def second() -> None:
        with folder_lock(folder):
            got.set()

    with folder_lock(folder):
        t = threading.Thread(target=second)
        t.start()
        assert not got.wait(0.3)
    assert got.wait(10.0)
    t.join()
    assert (tmp_path / "cache.lock").is_file()


def test_incomplete_cache_is_refused(tmp_path: Path) -> None:
    """A folder without keyframes.json (never made or interrupted) is no cache."""
    (tmp_path / "000000.msgpack").write_bytes(b"x")
    with pytest.raises(DatasetError, match="no complete keyframe cache"):
        read_keyframes(tmp_path)
    (tmp_path / "keyframes.json").write_text("{}")
    with pytest.raises(DatasetError, match="malformed"):
        read_keyframes(tmp_path)


@pytest.mark.skipif(not TUM.is_dir(), reason=f"{TUM} absent")
def test_tum_excerpt(tmp_path: Path) -> None:
    """A real TUM folder: no labels (``none``), no odometry; every keyframe has ground truth."""
    reader = DatasetReader(TUM)
    assert auto_labels(reader) == "none"
    cache = cache_keyframes(TUM, tmp_path / "tum", robot_id="tum", session_id="a", stop=20)
    assert len(cache) >= 2 and all(T is not None for T in cache.truth)
    msg = cache.message(0)
    assert msg.T_odom_base is None and msg.pose_source == "init"
