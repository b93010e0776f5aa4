"""A ROS 2 robot as rmw_zenoh puts it on Zenoh, for tests: CDR-serialised sensor_msgs and nav_msgs
messages (built with rosbags' type store) on ``<domain>/<topic>/<DDS type>/<hash>`` keys."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import zenoh
from peers import open_client
from rosbags.typesys import Stores, get_typestore

from wardmap.edge.ros2live import dds_type_name
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import transform_to_tum

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
HASH = "RIHS01_" + "0" * 64  # the subscriber matches any type hash


def header(stamp: float, frame: str = "camera_color_optical_frame") -> Any:
    ns = round(stamp * 1e6) * 1000
    time_msg = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=time_msg, frame_id=frame)


def image(stamp: float, pixels: np.ndarray, encoding: str) -> Any:
    """A ``sensor_msgs/Image`` of (H, W[, C]) ``pixels``."""
    h, w = pixels.shape[:2]
    data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
    return T["sensor_msgs/msg/Image"](header=header(stamp), height=h, width=w, encoding=encoding,
                                      is_bigendian=0, step=data.size // h, data=data)


def camera_info(cam: PinholeCamera) -> Any:
    """A ``sensor_msgs/CameraInfo`` (plumb_bob) of ``cam``."""
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    K = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1])
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(0.5), height=cam.height, width=cam.width, distortion_model="plumb_bob",
        d=np.array(cam.distortion, np.float64), k=K,
        r=np.eye(3).reshape(-1), p=np.zeros(12), binning_x=0, binning_y=0, roi=roi)


def odometry(stamp: float, pose: np.ndarray) -> Any:
    """A ``nav_msgs/Odometry`` with ``pose`` (4, 4) as ``T_odom_base``."""
    v = transform_to_tum(pose)
    p = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=v[0], y=v[1], z=v[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=v[3], y=v[4], z=v[5], w=v[6]))
    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T["nav_msgs/msg/Odometry"](
        header=header(stamp, "odom"), child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=p, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)))


class Robot:
    """A ROS 2 robot as rmw_zenoh puts it on Zenoh: ``put(topic, msg)`` publishes the CDR bytes on
    ``<domain>/<topic>/<dds type>/<hash>``."""

    def __init__(self, endpoint: str, domain: int = 0) -> None:
        self.session = open_client(endpoint)
        self.domain = domain

    def put(self, topic: str, msg: Any) -> None:
        msgtype = msg.__msgtype__
        key = f"{self.domain}/{topic.strip('/')}/{dds_type_name(msgtype)}/{HASH}"
        # reliable and blocking, so a loaded test host delays messages rather than drops them
        self.session.put(key, bytes(TS.serialize_cdr(msg, msgtype)),
                         congestion_control=zenoh.CongestionControl.BLOCK)

    def keep_putting(self, topic: str, msg: Any, until: threading.Event) -> threading.Thread:
        """Put ``msg`` every 50 ms until ``until`` is set (a camera driver's CameraInfo)."""
        def run() -> None:
            while not until.wait(0.05):
                self.put(topic, msg)
        t = threading.Thread(target=run, daemon=True)
        t.start()
        return t


