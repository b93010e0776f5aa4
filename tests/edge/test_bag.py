"""ROS recordings as a frame source (edge/bag.py), on small synthetic recordings written with
``rosbags`` (tools/bags.py's BagWriter): encodings, formats, calibration, errors, order."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")

from wardmap.edge.bag import (
    COMPRESSED,
    IMAGE,
    BagSource,
    BagSourceConfig,
    decode_colour,
    decode_depth,
)
from wardmap.edge.stream import FrameStream, OdometrySample
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import DatasetError
from wardmap.shared.se3 import make_transform, so3_exp, yaw_transform
from wardmap.tools.bags import BagWriter

CAM = PinholeCamera(16, 12, 20.0, 21.0, 7.5, 5.5, (0.1, -0.05, 0.001, 0.002, 0.01))
T_BASE_RGB = make_transform(so3_exp([-1.5, 0.1, -1.4]), [0.12, 0.0, 1.05])


def _images(n: int, seed: int = 0) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """``n`` frames at 30 Hz: random colour, depth in [0.5, 4] m quantised to 1 mm, some holes."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        rgb = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
        depth = np.round(rng.uniform(0.5, 4.0, (12, 16)), 3).astype(np.float32)
        depth[rng.random((12, 16)) < 0.1] = 0.0
        out.append((round(50.0 + i / 30, 6), rgb, depth))
    return out


def _write(path: Path, frames: list[tuple[float, np.ndarray, np.ndarray]], *, camera_info: bool = True,
           odometry: str = "odom", log_order: list[int] | None = None, **kw: Any) -> None:
    with BagWriter(path, **kw) as w:
        if camera_info:
            w.write_camera_info(frames[0][0], CAM)
        w.write_tf_static(frames[0][0], T_BASE_RGB)
        order = log_order or list(range(len(frames)))
        for k, i in enumerate(order):
            stamp, rgb, depth = frames[i]
            log_t = frames[k][0]  # written at the k-th slot of the recording
            w.write_frame(stamp, rgb, depth, log_stamp=log_t)
        for k in range(int(len(frames) / 30 * 50) + 3) if odometry else ():
            t = round(50.0 + k / 50, 6)
            write = w.write_odometry if odometry == "odom" else w.write_tf_odometry
            write(t, yaw_transform(0.1 * k, 0.0, 0.01 * k), log_stamp=t + 0.005)


@pytest.mark.parametrize("name", ["r2", "one.mcap", "r1.bag"])
@pytest.mark.parametrize("depth_encoding", ["32FC1", "16UC1"])
def test_frames_calibration_and_odometry_round_trip_in_every_format(
        tmp_path: Path, name: str, depth_encoding: str) -> None:
    """A ROS 2 bag (sqlite3), one MCAP file and a ROS 1 bag, with 32FC1 and 16UC1 depth: colour
    comes back byte-identical, depth exact (the depths are whole millimetres), the camera
    from CameraInfo, ``T_base_rgb`` from /tf_static, odometry from nav_msgs/Odometry."""
    frames = _images(6)
    _write(tmp_path / name, frames, depth_encoding=depth_encoding)  # type: ignore[arg-type]
    source = BagSource(tmp_path / name)
    assert source.calibration.rgb == CAM
    assert source.calibration.T_base_rgb is not None
    np.testing.assert_allclose(source.calibration.T_base_rgb, T_BASE_RGB, atol=1e-12)
    assert source.has_odometry and source.frame_count == 6
    events = list(source.events())
    got = [e for e in events if not isinstance(e, OdometrySample)]
    assert len(got) == 6
    for (stamp, rgb, depth), f in zip(frames, got, strict=True):
        assert f.stamp == stamp
        np.testing.assert_array_equal(f.rgb, rgb)  # type: ignore[union-attr]
        np.testing.assert_allclose(f.depth_m, depth, atol=1e-6)  # type: ignore[union-attr]
    odo = [e for e in events if isinstance(e, OdometrySample)]
    assert len(odo) > 6 and odo[3].stamp == 50.06
    np.testing.assert_allclose(odo[3].T_odom_base, yaw_transform(0.3, 0.0, 0.03), atol=1e-12)


@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_compressed_colour_is_decoded(tmp_path: Path, fmt: str) -> None:
    """CompressedImage colour: PNG comes back exact, JPEG close (lossy) on a smooth image."""
    frames = [(s, np.repeat(np.linspace(0, 255, 16, dtype=np.uint8)[None, :, None], 12, 0).repeat(3, 2), d)
              for s, _, d in _images(3)]
    _write(tmp_path / "c", frames, rgb_format=fmt)  # type: ignore[arg-type]
    got = [e for e in BagSource(tmp_path / "c").events() if not isinstance(e, OdometrySample)]
    assert len(got) == 3
    err = np.abs(got[0].rgb.astype(int) - frames[0][1]).max()  # type: ignore[union-attr]
    assert err == 0 if fmt == "png" else err <= 12


def _image_msg(encoding: str, pixels: np.ndarray, pad: int = 0) -> Any:
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    h, w = pixels.shape[:2]
    rows = np.ascontiguousarray(pixels).view(np.uint8).reshape(h, -1)
    data = np.concatenate([rows, np.zeros((h, pad), np.uint8)], axis=1).reshape(-1)
    header = ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                             frame_id="cam")
    return ts.types["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding=encoding,
                                             is_bigendian=0, step=rows.shape[1] + pad, data=data)


def test_colour_encodings_give_rgb_and_respect_row_padding() -> None:
    """rgb8, bgr8 (channels swapped), mono8 (grey in all three) and rows padded beyond width."""
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
    np.testing.assert_array_equal(decode_colour(_image_msg("rgb8", rgb, pad=3), IMAGE, "t"), rgb)
    np.testing.assert_array_equal(decode_colour(_image_msg("bgr8", rgb[:, :, ::-1]), IMAGE, "t"), rgb)
    grey = rgb[:, :, 0]
    np.testing.assert_array_equal(decode_colour(_image_msg("mono8", grey, pad=1), IMAGE, "t"),
                                  np.repeat(grey[:, :, None], 3, axis=2))
    with pytest.raises(DatasetError, match="yuv422"):
        decode_colour(_image_msg("yuv422", rgb[:, :, :2]), IMAGE, "t")


def test_depth_encodings_give_metres_and_no_data_as_zero() -> None:
    """16UC1 in millimetres (0 = none) and 32FC1 in metres (NaN, inf, negative = none)."""
    mm = np.array([[0, 1000, 2500]], np.uint16)
    got = decode_depth(_image_msg("16UC1", mm, pad=2), IMAGE, 0.001, "t")
    np.testing.assert_allclose(got, [[0, 1.0, 2.5]])
    m = np.array([[np.nan, np.inf, -1.0, 1.25]], np.float32)
    np.testing.assert_array_equal(decode_depth(_image_msg("32FC1", m), IMAGE, 0.001, "t"), [[0, 0, 0, 1.25]])
    with pytest.raises(DatasetError, match="raw sensor_msgs/Image"):
        decode_depth(None, COMPRESSED, 0.001, "t")


def test_missing_camera_info_is_a_clear_error_and_a_calibration_file_replaces_it(tmp_path: Path) -> None:
    """Without CameraInfo the source refuses to open, naming the topic and the two remedies; a
    calibration.toml given instead is used as it is."""
    from wardmap.shared.dataset import Calibration, save_calibration

    _write(tmp_path / "b", _images(2), camera_info=False)
    needle = r"no sensor_msgs/CameraInfo on '/camera/color/camera_info'.*calibration"
    with pytest.raises(DatasetError, match=needle):
        BagSource(tmp_path / "b")
    save_calibration(tmp_path / "calibration.toml", Calibration(rgb=CAM, depth_scale=1000.0))
    source = BagSource(tmp_path / "b", BagSourceConfig(calibration=str(tmp_path / "calibration.toml")))
    assert source.calibration.rgb == CAM and source.calibration.T_base_rgb is None


def test_a_topic_that_does_not_exist_is_named_with_the_recording_topics(tmp_path: Path) -> None:
    """A wrong topic name: the error names it and lists the recording's topics and types; a
    topic of the wrong type is refused too."""
    _write(tmp_path / "b", _images(2))
    needle = r"no topic '/nope' \(rgb_topic\); its topics: .*/odom \(nav_msgs/msg/Odometry\)"
    with pytest.raises(DatasetError, match=needle):
        BagSource(tmp_path / "b", BagSourceConfig(rgb_topic="/nope"))
    with pytest.raises(DatasetError, match="carries nav_msgs/msg/Odometry"):
        BagSource(tmp_path / "b", BagSourceConfig(depth_topic="/odom"))
    with pytest.raises(DatasetError, match="recording not found"):
        BagSource(tmp_path / "missing.mcap")


def test_out_of_order_messages_give_the_same_frames_in_stamp_order(tmp_path: Path) -> None:
    """A recording whose frames were logged out of order (pairs swapped, odometry 5 ms late)
    streams the same frames with the same odometry poses as the one logged in order."""
    frames = _images(8)
    _write(tmp_path / "ordered", frames)
    _write(tmp_path / "shuffled", frames, log_order=[1, 0, 2, 4, 3, 5, 7, 6])
    runs = []
    for name in ("ordered", "shuffled"):
        with FrameStream(BagSource(tmp_path / name)) as stream:
            runs.append(list(stream))
        assert stream.counters() == {"received": 8, "dropped": 0, "late": 0, "source_dropped": 0}
    a, b = runs
    assert [i.stamp for i in a] == [i.stamp for i in b] == [f[0] for f in frames]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.frame.rgb, y.frame.rgb)  # type: ignore[union-attr]
        assert x.T_odom_base is not None and y.T_odom_base is not None
        np.testing.assert_array_equal(x.T_odom_base, y.T_odom_base)


def test_odometry_from_tf_when_the_recording_has_no_odometry_topic(tmp_path: Path) -> None:
    """A recording whose wheel odometry is only the /tf transform odom -> base_link streams the
    same odometry poses as one with nav_msgs/Odometry; a wrong odometry frame named explicitly is
    an error, and without odometry nothing is waited for."""
    frames = _images(6)
    _write(tmp_path / "odom", frames)
    _write(tmp_path / "tf", frames, odometry="tf")
    _write(tmp_path / "none", frames, odometry="")
    runs = []
    for name in ("odom", "tf"):
        source = BagSource(tmp_path / name)
        assert source.has_odometry and source.base_frame == "base_link"
        with FrameStream(source) as stream:
            runs.append(list(stream))
    for x, y in zip(*runs, strict=True):
        assert x.T_odom_base is not None and y.T_odom_base is not None
        np.testing.assert_allclose(x.T_odom_base, y.T_odom_base, atol=1e-12)
    with pytest.raises(DatasetError, match="no transform 'map' -> 'base_link'"):
        BagSource(tmp_path / "tf", BagSourceConfig(odom_topic="/tf", odom_frame="map"))
    assert not BagSource(tmp_path / "none").has_odometry


def test_colour_without_a_depth_partner_is_counted_as_dropped_by_the_source(tmp_path: Path) -> None:
    """Frame 5's depth image is stamped 25 ms after its colour (outside the 20 ms window): that
    colour image is left out, and the stream reports it as ``source_dropped``."""
    frames = _images(8)
    with BagWriter(tmp_path / "gap") as w:
        w.write_camera_info(frames[0][0], CAM)
        for i, (stamp, rgb, depth) in enumerate(frames):
            w.write_frame(stamp, rgb, depth, depth_stamp=round(stamp + 0.025, 6) if i == 5 else None)
    source = BagSource(tmp_path / "gap", BagSourceConfig(odom_topic=""))
    with FrameStream(source) as stream:
        stamps = [item.stamp for item in stream]
    assert stamps == [f[0] for i, f in enumerate(frames) if i != 5]
    assert source.dropped_frames == 1
    assert stream.counters() == {"received": 7, "dropped": 0, "late": 0, "source_dropped": 1}


def test_aligned_depth_pairs_as_soon_as_it_comes() -> None:
    """A depth image stamped like its colour image settles the pair at once (a camera's aligned
    depth); one stamped before it waits for a later depth image (a nearer one may still come)."""
    from rosbags.typesys import Stores, get_typestore

    from wardmap.edge.bag import FramePairer
    from wardmap.shared.dataset import Calibration

    types = get_typestore(Stores.ROS2_HUMBLE).types

    def msg(stamp: float, pixels: np.ndarray, encoding: str) -> Any:
        ns = round(stamp * 1e9)
        header = types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id="cam")
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        return types["sensor_msgs/msg/Image"](header=header, height=12, width=16, encoding=encoding,
                                              is_bigendian=0, step=data.size // 12, data=data)

    (s0, rgb, depth), (s1, _, _) = _images(2)
    pairer = FramePairer(BagSourceConfig(odom_topic=""), Calibration(rgb=CAM), "test")
    assert list(pairer.add(True, msg(s0, rgb, "rgb8"), IMAGE)) == []
    got = list(pairer.add(False, msg(s0, depth, "32FC1"), IMAGE))
    assert [f.stamp for f in got] == [s0]  # at once, not one frame later
    assert list(pairer.add(True, msg(s1, rgb, "rgb8"), IMAGE)) == []
    assert list(pairer.add(False, msg(s1 - 0.005, depth, "32FC1"), IMAGE)) == []  # before: waits
    got = list(pairer.add(False, msg(s1 + 0.030, depth, "32FC1"), IMAGE))
    assert [f.stamp for f in got] == [s1] and got[0].depth_stamp == pytest.approx(s1 - 0.005)
