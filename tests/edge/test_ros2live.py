"""Live ROS 2 topics over Zenoh (edge/ros2live.py): a real Zenoh router and a publisher that puts
CDR-serialised Image, CameraInfo and Odometry messages on rmw_zenoh's key expressions, as a robot
running rmw_zenoh does (loopback, free port, multicast scouting and shared memory off)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from peers import router_on_thread

from wardmap.edge.bag import BagSourceConfig
from wardmap.edge.live import SourceLostError
from wardmap.edge.ros2live import (
    Ros2Options,
    Ros2Source,
    dds_type_name,
    msgtype_of_dds,
    parse_spec,
    topic_key,
)
from wardmap.edge.stream import OdometrySample
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Frame
from wardmap.shared.errors import ConfigError
from wardmap.shared.se3 import yaw_transform

rosbags = pytest.importorskip("rosbags", reason="the ros extra (rosbags) is not installed")
from ros2robot import Robot, T, camera_info, header, image, odometry  # noqa: E402

W, H = 32, 24
CAMERA = PinholeCamera(W, H, 30.0, 30.0, 16.0, 12.0)


def test_keys_follow_rmw_zenoh_and_the_dds_bridge() -> None:
    opts = Ros2Options(domain_id=3)
    assert topic_key("/camera/color/image_raw", opts) == "3/camera/color/image_raw/*/*"
    assert topic_key("/odom", Ros2Options(key_format="ros2dds")) == "odom"
    assert dds_type_name("sensor_msgs/msg/Image") == "sensor_msgs::msg::dds_::Image_"
    assert msgtype_of_dds("nav_msgs::msg::dds_::Odometry_") == "nav_msgs/msg/Odometry"
    assert msgtype_of_dds("Image") is None
    with pytest.raises(ConfigError, match="ros_key_format"):
        Ros2Options(key_format="dds")


def test_the_domain_comes_from_the_config_else_ros_domain_id(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    assert parse_spec("ros2:", BagSourceConfig()) == Ros2Options(domain_id=7)
    got = parse_spec("ros2:tcp/10.0.0.5:7447", BagSourceConfig(ros_domain_id=2))
    assert (got.endpoint, got.domain_id) == ("tcp/10.0.0.5:7447", 2)
    monkeypatch.setenv("ROS_DOMAIN_ID", "x")
    with pytest.raises(ConfigError, match="ROS_DOMAIN_ID"):
        parse_spec("ros2:", BagSourceConfig())


@pytest.fixture
def robot() -> Iterator[tuple[str, Robot]]:
    with router_on_thread() as endpoint:
        bot = Robot(endpoint)
        try:
            yield endpoint, bot
        finally:
            bot.session.close()


def _frames(n: int) -> list[tuple[float, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(0)
    return [(10.0 + k / 30, rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
             rng.uniform(0.5, 4.0, (H, W)).astype(np.float32)) for k in range(n)]


@pytest.mark.parametrize("compressed", [False, True])
def test_frames_and_odometry_come_from_the_robots_topics(robot: tuple[str, Robot], compressed: bool) -> None:
    endpoint, bot = robot
    cfg = BagSourceConfig(rgb_topic="/camera/color/image_raw/compressed" if compressed else
                          "/camera/color/image_raw", ros_stall_s=3.0)
    stop, connected = threading.Event(), threading.Event()
    info = bot.keep_putting(cfg.camera_info_topic, camera_info(CAMERA), connected)
    source = Ros2Source(cfg, parse_spec(f"ros2:{endpoint}", cfg), stop)  # waits for the CameraInfo
    connected.set()
    info.join()
    cam = source.calibration.rgb
    assert (cam.width, cam.height, cam.fx, cam.cx) == (W, H, 30.0, 16.0)
    assert source.live and source.has_odometry
    frames = _frames(8)
    for k, (stamp, rgb, depth) in enumerate(frames):
        bot.put("/odom", odometry(stamp - 0.01, yaw_transform(0.1 * k, 0.0, 0.0)))
        if compressed:
            ok, jpeg = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            assert ok
            bot.put(cfg.rgb_topic, T["sensor_msgs/msg/CompressedImage"](
                header=header(stamp), format="png", data=np.asarray(jpeg, np.uint8).reshape(-1)))
        else:
            bot.put(cfg.rgb_topic, image(stamp, rgb, "rgb8"))
        bot.put(cfg.depth_topic, image(stamp, depth, "32FC1"))
    got: list[Frame] = []
    odo: list[OdometrySample] = []
    for ev in source.events():
        if isinstance(ev, OdometrySample):
            odo.append(ev)
        elif isinstance(ev, Frame):
            got.append(ev)
        # Each depth image is stamped like its colour image, so every pair settles when its depth
        # comes, the last one too. Topics are not ordered among themselves (one odometry sample
        # may come after the next image): wait for all.
        if len(got) == len(frames) and len(odo) == len(frames):
            stop.set()
    assert source._session is None  # the session is closed when the events end
    assert [f.stamp for f in got] == [round(s, 6) for s, _, _ in frames]
    for frame, (_, rgb, depth) in zip(got, frames, strict=False):
        np.testing.assert_array_equal(frame.rgb, rgb)  # rgb8 and PNG are exact
        np.testing.assert_array_equal(frame.depth_m, depth)
    np.testing.assert_allclose([o.stamp for o in odo], [s - 0.01 for s, _, _ in frames], atol=1e-6)
    np.testing.assert_allclose(odo[3].T_odom_base, yaw_transform(0.3, 0.0, 0.0), atol=1e-9)


def test_no_images_for_a_while_is_a_lost_source(robot: tuple[str, Robot]) -> None:
    endpoint, bot = robot
    cfg = BagSourceConfig(ros_stall_s=0.5, odom_topic="")
    stop, connected = threading.Event(), threading.Event()
    info = bot.keep_putting(cfg.camera_info_topic, camera_info(CAMERA), connected)
    source = Ros2Source(cfg, parse_spec(f"ros2:{endpoint}", cfg), stop)
    connected.set()
    info.join()
    t0 = time.monotonic()
    with pytest.raises(SourceLostError, match=r"no images on /camera/color/image_raw for 0\.5 s"):
        list(source.events())
    assert 0.4 < time.monotonic() - t0 < 3.0 and source._session is None


def test_no_camera_info_says_which_topic_and_what_to_do(robot: tuple[str, Robot]) -> None:
    endpoint, _ = robot
    cfg = BagSourceConfig(ros_stall_s=0.3, camera_info_topic="/cam/info")
    with pytest.raises(SourceLostError, match=r"no sensor_msgs/CameraInfo on /cam/info .*--calibration"):
        Ros2Source(cfg, parse_spec(f"ros2:{endpoint}", cfg), threading.Event())


def test_an_unreachable_router_is_a_lost_source() -> None:
    from procs import free_port

    cfg = BagSourceConfig(ros_stall_s=0.3)
    with pytest.raises(SourceLostError, match="cannot reach the ROS 2 Zenoh router"):
        Ros2Source(cfg, parse_spec(f"ros2:tcp/127.0.0.1:{free_port()}", cfg), threading.Event())
