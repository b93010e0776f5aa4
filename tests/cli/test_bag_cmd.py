"""ROS recordings end to end through the command: ``wardmap dataset to-bag`` writes a simulated
scenario and the TUM excerpt as a ROS 2 bag and an MCAP file (with rosbags), then ``wardmap
track`` and ``wardmap edge --source bag:`` on them give the trajectory the folder gives;
``dataset from-bag`` writes the folder back; bad input is one line and exit code 1."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from procs import child_env, one_line_error, router_process, wardmap, wardmap_cmd

pytest.importorskip("rosbags")

from wardmap.shared.dataset import DatasetReader, save_calibration
from wardmap.shared.metrics import ate

pytestmark = pytest.mark.timeout(300)

TUM = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "tum_fr1_rpy_s3_first100"
SIM_FRAMES = 12


def _ok(*args: str) -> str:
    done = wardmap(*args)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    return done.stdout


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Twelve frames of aisle_slow_1 (seed 0) from ``wardmap sim``: colour, depth, thermal,
    odometry and the camera mount."""
    path = tmp_path_factory.mktemp("bagcmd") / "aisle"
    _ok("sim", "--scenario", "aisle_slow_1", "--out", str(path), "--frames", str(SIM_FRAMES))
    return path


def _trajectory(path: Path) -> np.ndarray:
    return np.loadtxt(path, comments="#")


def _track(source: str, out: Path, *extra: str) -> np.ndarray:
    _ok("track", "--source", source, "--out", str(out), *extra)
    return _trajectory(out)


def test_sim_scenario_as_ros2_bag_and_mcap_tracks_like_the_folder(sim: Path, tmp_path: Path) -> None:
    """Raw colour with 32FC1 depth in a ROS 2 bag (sqlite3) and one MCAP file: the trajectory is
    the folder's to its last printed digit (same frames, same odometry poses, same camera mount); PNG colour
    with 16UC1 millimetre depth in a ROS 1 bag is within 1 mm ATE of it (depth quantised)."""
    _ok("dataset", "to-bag", str(sim), "--out", str(tmp_path / "ros2"))
    _ok("dataset", "to-bag", str(sim), "--out", str(tmp_path / "sim.mcap"))
    _ok("dataset", "to-bag", str(sim), "--out", str(tmp_path / "sim.bag"), "--rgb", "png", "--depth", "16UC1")
    folder = _track(str(sim), tmp_path / "folder.txt")
    assert len(folder) == SIM_FRAMES
    for name in ("ros2", "sim.mcap"):
        # the file's 9 decimals: OpenCV 5 can differ by one ulp between the two decoders' arrays,
        # which may flip the last printed digit (seen once in 96 values), nothing more
        np.testing.assert_allclose(_track(f"bag:{tmp_path / name}", tmp_path / f"{name}.txt"), folder,
                                   rtol=0, atol=1.5e-9)
    mm = _track(f"bag:{tmp_path / 'sim.bag'}", tmp_path / "mm.txt")
    from wardmap.shared.se3 import transform_from_tum

    def poses(a: np.ndarray) -> np.ndarray:
        return np.stack([transform_from_tum(r[1:]) for r in a])

    res = ate(mm[:, 0], poses(mm), folder[:, 0], poses(folder), align="none")
    assert res.rmse <= 1e-3


def test_from_bag_writes_the_folder_back(sim: Path, tmp_path: Path) -> None:
    """to-bag then from-bag (MCAP, raw colour, 32FC1 depth): the same colour and depth images,
    stamps, intrinsics, camera mount and odometry (to the microsecond and the file's 9 decimals)."""
    _ok("dataset", "to-bag", str(sim), "--out", str(tmp_path / "sim.mcap"))
    _ok("dataset", "from-bag", str(tmp_path / "sim.mcap"), "--out", str(tmp_path / "back"))
    a, b = DatasetReader(sim), DatasetReader(tmp_path / "back")
    assert list(a.stamps) == list(b.stamps)
    assert a.calibration.rgb == b.calibration.rgb
    assert a.calibration.T_base_rgb is not None and b.calibration.T_base_rgb is not None
    np.testing.assert_allclose(b.calibration.T_base_rgb, a.calibration.T_base_rgb, atol=1e-9)
    for i in range(len(a)):
        fa, fb = a.frame(i), b.frame(i)
        np.testing.assert_array_equal(fa.rgb, fb.rgb)
        np.testing.assert_array_equal(fa.depth_m, fb.depth_m)
    oa, ob = a.odometry(), b.odometry()
    assert oa is not None and ob is not None
    n = len(ob[0])  # to-bag writes odometry up to one sample past the last frame
    np.testing.assert_array_equal(oa[0][:n], ob[0])
    np.testing.assert_allclose(oa[1][:n], ob[1], atol=1e-8)


@pytest.mark.skipif(not TUM.is_dir(), reason="the TUM excerpt (../shared/data) is not here")
def test_tum_excerpt_as_ros2_bag_and_mcap_tracks_like_the_folder(tmp_path: Path) -> None:
    """The first 6 frames of the TUM fr1/rpy excerpt (no odometry, distorted fr1 camera): a ROS 2
    bag and an MCAP file with PNG colour give the folder's trajectory exactly, given the folder's
    calibration (a recording carries no rolling-shutter readout; the folder's name gives the
    Kinect's)."""
    _ok("dataset", "to-bag", str(TUM), "--out", str(tmp_path / "tum"), "--max-frames", "6")
    _ok("dataset", "to-bag", str(TUM), "--out", str(tmp_path / "tum.mcap"), "--max-frames", "6",
        "--rgb", "png")
    calib = tmp_path / "calibration.toml"
    save_calibration(calib, DatasetReader(TUM).calibration)
    folder = _track(str(TUM), tmp_path / "folder.txt", "--max-frames", "6")
    assert len(folder) == 6
    for name in ("tum", "tum.mcap"):
        bag = _track(f"bag:{tmp_path / name}", tmp_path / f"{name}.txt", "--calibration", str(calib))
        np.testing.assert_array_equal(bag, folder)


def test_bad_recordings_and_topics_are_one_line_errors(sim: Path, tmp_path: Path) -> None:
    """A topic that does not exist (track and edge), a missing recording and a recording without
    CameraInfo: one line on stderr, exit code 1, nothing tracked."""
    bag = tmp_path / "sim.mcap"
    _ok("dataset", "to-bag", str(sim), "--out", str(bag), "--max-frames", "2")
    out = tmp_path / "t.txt"
    one_line_error(wardmap("track", "--source", f"bag:{bag}", "--out", str(out), "--rgb-topic", "/nope"),
                   "no topic '/nope' (rgb_topic); its topics:", "track")
    one_line_error(wardmap("edge", "--robot", "r1", "--source", f"bag:{bag}", "--connect", "tcp/127.0.0.1:9",
                           "--outbox", str(tmp_path / "ob"), "--depth-topic", "/camera/depth"),
                   "no topic '/camera/depth' (depth_topic)", "edge")
    one_line_error(wardmap("track", "--source", f"bag:{tmp_path / 'none.mcap'}", "--out", str(out)),
                   "recording not found", "track")
    no_info = wardmap("track", "--source", f"bag:{bag}", "--out", str(out), "--camera-info-topic", "/info")
    one_line_error(no_info, "no sensor_msgs/CameraInfo on '/info'", "track")
    assert not out.exists() and not (tmp_path / "ob").exists()


@pytest.mark.integration
@pytest.mark.timeout(180)
def test_edge_on_a_bag_sends_the_keyframes_the_folder_gives(sim: Path, tmp_path: Path) -> None:
    """``wardmap edge --source bag:`` (MCAP) and ``--source FOLDER`` through a real router with no
    server: both outboxes keep the same keyframes: the same stamps, and odom-frame camera poses and
    wheel-odometry base poses (time aligned from the bag's nav_msgs/Odometry) equal to 1e-9 m (the
    camera mount travels as a /tf_static quaternion, so the last bits differ)."""
    from wardmap.edge.outbox import Outbox
    from wardmap.shared.wire import decode_keyframe

    pytest.importorskip("zenoh")
    _ok("dataset", "to-bag", str(sim), "--out", str(tmp_path / "sim.mcap"))
    config = tmp_path / "edge.toml"
    config.write_text("[agent]\nflush_timeout_s = 0.2\n")
    kept = []
    with router_process(15.0) as (_, endpoint):
        for name, source in (("folder", str(sim)), ("bag", f"bag:{tmp_path / 'sim.mcap'}")):
            done = subprocess.run(
                wardmap_cmd("edge", "--robot", "r1", "--source", source, "--connect", endpoint,
                            "--outbox", str(tmp_path / name), "--config", str(config), "--privacy", "off"),
                capture_output=True, text=True, timeout=120, env=child_env())
            assert done.returncode == 0, done.stderr
            with Outbox.open(tmp_path / name / "outbox.sqlite") as outbox:
                kept.append([decode_keyframe(item.payload) for item in outbox.pending(10_000)])
    folder, bag = kept
    assert len(folder) >= 2 and len(bag) == len(folder)
    for a, b in zip(folder, bag, strict=True):
        assert a.stamp == b.stamp
        np.testing.assert_allclose(a.T_odom_camera, b.T_odom_camera, rtol=0, atol=1e-9)
        assert a.T_odom_base is not None and b.T_odom_base is not None  # the bag's wheel odometry
        np.testing.assert_allclose(a.T_odom_base, b.T_odom_base, rtol=0, atol=1e-9)


def test_topics_from_the_config_source_table_and_the_options(sim: Path, tmp_path: Path) -> None:
    """A recording on other topic names: the config's [source] table names them and the
    command-line option overrides the table (here a wrong table entry corrected by the option)."""
    from wardmap.edge.bag import BagSourceConfig
    from wardmap.shared.dataset import DatasetReader
    from wardmap.tools.bags import BagWriter

    topics = BagSourceConfig(rgb_topic="/cam/rgb", depth_topic="/cam/depth", camera_info_topic="/cam/info")
    reader = DatasetReader(sim)
    with BagWriter(tmp_path / "named.mcap", topics=topics) as w:
        w.write_camera_info(float(reader.stamps[0]), reader.calibration.rgb)
        for i in range(3):
            f = reader.frame(i)
            w.write_frame(f.stamp, f.rgb, f.depth_m)
    config = tmp_path / "source.toml"
    config.write_text('[source]\nrgb_topic = "/cam/rgb"\ndepth_topic = "/cam/nope"\n'
                      'camera_info_topic = "/cam/info"\n')
    out = tmp_path / "t.txt"
    source = f"bag:{tmp_path / 'named.mcap'}"
    one_line_error(wardmap("track", "--source", source, "--out", str(out), "--config", str(config)),
                   "no topic '/cam/nope' (depth_topic)", "track")
    _ok("track", "--source", source, "--out", str(out), "--config", str(config),
        "--depth-topic", "/cam/depth")
    assert len(_trajectory(out)) == 3
