"""Live ROS 2 topics over Zenoh, without a ROS installation (``--source ros2:[ENDPOINT]``).

A robot running ROS 2 with ``rmw_zenoh`` publishes each topic on the Zenoh key
``<domain_id>/<topic without its leading />/<DDS type name>/<type hash>`` (rmw_zenoh's
docs/design.md, "Topic and Service name mapping to Zenoh key expressions"), e.g.
``0/camera/color/image_raw/sensor_msgs::msg::dds_::Image_/RIHS01_...``, with the message
serialised as CDR (with its 4-byte encapsulation header). This source opens a Zenoh *client*
session to ``ENDPOINT`` (default ``tcp/127.0.0.1:7447``, the rmw_zenoh router ``rmw_zenohd``
on the robot; multicast scouting and shared memory off), subscribes to
``<domain>/<topic>/*/*`` for the colour, depth, CameraInfo and odometry topics (any type name and
hash: the type is read from the key) and deserialises the payloads with ``rosbags``' type
store (extra ``ros``), as the recording reader does (:mod:`wardmap.edge.bag`: same decoding,
same colour/depth pairing, same ``[source]`` table and options).

A robot on a DDS middleware reaches the same source through ``zenoh-bridge-ros2dds``, which
publishes each topic on the key ``<topic without its leading />`` (no domain, no type):
``key_format = "ros2dds"``; the type is then ``CompressedImage`` for a colour topic ending in
``/compressed`` and ``Image`` otherwise.

Calibration: the first ``CameraInfo`` (waited for up to ``stall_s`` at connect), or a
``calibration.toml`` (``calibration``), which also gives the camera mount ``T_base_rgb``
(``/tf_static`` is not read live: without the file, odometry cannot be used and a warning says
so). Odometry: ``nav_msgs/Odometry`` on ``odom_topic`` (default ``/odom``; ``""`` = none).

Threads: Zenoh's callbacks only put ``(key, payload)`` into a bounded queue
(:data:`QUEUE_SIZE`; when full the message is dropped and counted in ``dropped_messages``);
:meth:`Ros2Source.events` (the stream's producer thread) deserialises and pairs. No colour image
for ``stall_s`` seconds is :class:`~wardmap.edge.live.SourceLostError` (the daemon's reconnect loop
logs it and re-subscribes).
"""

from __future__ import annotations

import json
import logging
import os
import queue
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Final

from wardmap.edge.bag import (
    CAMERA_INFO,
    COMPRESSED,
    IMAGE,
    ODOMETRY,
    BagSourceConfig,
    FramePairer,
    camera_from_info,
    import_rosbags,
    odometry_sample,
)
from wardmap.edge.live import Connector, SourceLostError
from wardmap.edge.stream import SourceEvent
from wardmap.shared.dataset import Calibration, FrameSource, load_calibration
from wardmap.shared.errors import ConfigError
from wardmap.shared.zenoh_config import client_config

log = logging.getLogger(__name__)

SOURCE_PREFIX: Final = "ros2:"
DEFAULT_ENDPOINT: Final = "tcp/127.0.0.1:7447"
"""rmw_zenoh's router on the robot."""
KEY_FORMATS: Final = ("rmw_zenoh", "ros2dds")
QUEUE_SIZE: Final = 256
"""Messages waiting for the producer thread at most (about 2 s of a 30 Hz camera and 50 Hz odometry)."""
MAX_MESSAGE_BYTES: Final = 64 << 20
"""Largest ROS message the session takes (a 4K ``32FC1`` depth image is 33 MB); wardmap's own
sessions keep the wire's 4 MiB limit."""
POLL_S: Final = 0.2
"""Longest single wait for a message (a stop request is seen this soon)."""


@dataclass(frozen=True)
class Ros2Options:
    """What a live ROS 2 source needs beside the topics (``[source]`` table keys).

    Attributes:
        endpoint: the Zenoh router to connect to.
        domain_id: the ROS domain (``ROS_DOMAIN_ID``; default 0).
        key_format: ``rmw_zenoh`` or ``ros2dds`` (zenoh-bridge-ros2dds).
        stall_s: no colour image for this long (seconds) means the robot's camera is gone.
    """

    endpoint: str = DEFAULT_ENDPOINT
    domain_id: int = 0
    key_format: str = "rmw_zenoh"
    stall_s: float = 5.0

    def __post_init__(self) -> None:
        if self.key_format not in KEY_FORMATS:
            raise ConfigError(f"source.ros_key_format must be one of {', '.join(KEY_FORMATS)}, "
                              f"got {self.key_format!r}")
        if not 0 <= self.domain_id <= 232:
            raise ConfigError(f"ROS domain id must be in 0..232, got {self.domain_id}")
        if not self.stall_s > 0:
            raise ConfigError(f"source.ros_stall_s must be > 0, got {self.stall_s}")


def parse_spec(spec: str, config: BagSourceConfig) -> Ros2Options:
    """``ros2:`` or ``ros2:ENDPOINT`` with the ``[source]`` table's ROS keys."""
    endpoint = spec.removeprefix(SOURCE_PREFIX) or DEFAULT_ENDPOINT
    domain = config.ros_domain_id
    if domain is None:
        text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
        if not text.isdigit():
            raise ConfigError(f"ROS_DOMAIN_ID must be a number, got {text!r}")
        domain = int(text)
    return Ros2Options(endpoint=endpoint, domain_id=domain, key_format=config.ros_key_format,
                       stall_s=config.ros_stall_s)


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the key's type chunk)."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def msgtype_of_dds(name: str) -> str | None:
    """``sensor_msgs::msg::dds_::Image_`` -> ``sensor_msgs/msg/Image``; None if not that shape."""
    parts = name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        return None
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def topic_key(topic: str, options: Ros2Options) -> str:
    """The Zenoh key expression a subscriber to ``topic`` uses."""
    name = topic.strip("/")
    if not name:
        raise ConfigError(f"bad ROS topic {topic!r}")
    if options.key_format == "ros2dds":
        return name
    return f"{options.domain_id}/{name}/*/*"


class Ros2Source:
    """One Zenoh session subscribed to a robot's topics (module docstring); a live
    :class:`~wardmap.edge.stream.StreamSource` whose events end when ``stop`` is set.

    Attributes:
        dropped_messages: messages dropped because the producer thread was behind.
        dropped_colour: colour images among them.
        skipped: frames left out by reason (``unpaired``, ``wrong_type``).
    """

    live = True
    frame_count: int | None = None
    dataset: FrameSource | None = None

    def __init__(self, config: BagSourceConfig, options: Ros2Options, stop: threading.Event) -> None:
        """Opens the session and waits for the CameraInfo (unless a calibration file is given).

        Raises:
            SourceLostError: the router cannot be reached, or no CameraInfo came within ``stall_s``.
            ConfigError: rosbags or eclipse-zenoh is not installed.
        """
        self.cfg = config
        self.options = options
        self.name = f"{SOURCE_PREFIX}{options.endpoint}"
        self.skipped: Counter[str] = Counter()
        self.dropped_messages = 0
        self.dropped_colour = 0
        self._stop = stop
        self._queue: queue.Queue[tuple[str, str, bytes]] = queue.Queue(maxsize=QUEUE_SIZE)
        _, typesys = import_rosbags()
        self._typestore = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
        odom = "/odom" if config.odom_topic is None else config.odom_topic
        self._odom_topic = odom
        self.has_odometry = bool(odom)
        self._roles = {config.rgb_topic: "rgb", config.depth_topic: "depth"}
        if odom:
            self._roles[odom] = "odom"
        if not config.calibration:
            self._roles.setdefault(config.camera_info_topic, "info")
        self._session: Any = None
        self._open()
        try:
            self.calibration = self._calibration()
        except BaseException:
            self.close()
            raise
        if self.has_odometry and self.calibration.T_base_rgb is None:
            log.warning("%s: no camera mount T_base_rgb (give a calibration.toml with [base]): wheel "
                        "odometry on %s cannot be used", self.name, odom)

    def _open(self) -> None:
        try:
            import zenoh
        except ImportError as exc:  # a dependency of wardmap; only a broken install lacks it
            raise ConfigError("the ros2: source needs eclipse-zenoh") from exc
        ours = client_config([self.options.endpoint])
        ours["transport"]["link"]["rx"]["max_message_size"] = MAX_MESSAGE_BYTES  # images, not keyframes
        cfg = zenoh.Config.from_json5(json.dumps(ours))
        try:
            self._session = zenoh.open(cfg)
        except zenoh.ZError as exc:
            raise SourceLostError(f"cannot reach the ROS 2 Zenoh router at {self.options.endpoint}: "
                             f"{str(exc).split(' at /', 1)[0]}") from exc
        for topic, role in self._roles.items():
            self._session.declare_subscriber(topic_key(topic, self.options), self._callback(topic, role))

    def _callback(self, topic: str, role: str) -> Any:
        def on_sample(sample: Any) -> None:  # a Zenoh thread: enqueue only
            try:
                self._queue.put_nowait((role, str(sample.key_expr), sample.payload.to_bytes()))
            except queue.Full:
                self.dropped_messages += 1
                self.dropped_colour += role == "rgb"
        return on_sample

    @property
    def dropped_frames(self) -> int:
        """Frames lost before the stream: colour images dropped at the full queue, or unpaired
        (a dropped depth image shows as an unpaired colour image)."""
        return self.dropped_colour + self.skipped["unpaired"]

    def close(self) -> None:
        """Close the Zenoh session (idempotent; subscribers go with it)."""
        session, self._session = self._session, None
        if session is not None:
            session.close()

    def _msgtype(self, role: str, key: str) -> str | None:
        """The message type of a sample on ``key``, or None for one this source does not read."""
        if self.options.key_format == "rmw_zenoh":
            return msgtype_of_dds(key.split("/")[-2])
        if role == "rgb" and key.endswith("/compressed"):
            return COMPRESSED
        return {"rgb": IMAGE, "depth": IMAGE, "info": CAMERA_INFO, "odom": ODOMETRY}[role]

    def _messages(self, timeout_s: float) -> Iterator[tuple[str, str, Any]]:
        """``(role, msgtype, message)`` as they come, until ``stop`` or ``timeout_s`` without one."""
        deadline = time.monotonic() + timeout_s
        while not self._stop.is_set() and time.monotonic() < deadline:
            try:
                role, key, payload = self._queue.get(timeout=POLL_S)
            except queue.Empty:
                continue
            msgtype = self._msgtype(role, key)
            wanted = {"rgb": (IMAGE, COMPRESSED), "depth": (IMAGE,), "info": (CAMERA_INFO,),
                      "odom": (ODOMETRY,)}[role]
            if msgtype not in wanted:
                self.skipped["wrong_type"] += 1
                if self.skipped["wrong_type"] == 1:
                    log.warning("%s: %s carries %s, expected %s: ignored", self.name, key, msgtype,
                                " or ".join(wanted))
                continue
            try:
                msg = self._typestore.deserialize_cdr(payload, msgtype)
            except Exception as exc:  # rosbags raises several kinds for a bad payload
                self.skipped["undecodable"] += 1
                log.warning("%s: cannot decode a %s on %s: %s", self.name, msgtype, key, exc)
                continue
            deadline = time.monotonic() + timeout_s if role == "rgb" else deadline
            yield role, msgtype, msg

    def _calibration(self) -> Calibration:
        if self.cfg.calibration:
            return load_calibration(self.cfg.calibration)
        topic = self.cfg.camera_info_topic
        for role, _, msg in self._messages(self.options.stall_s):
            if role == "info":
                return Calibration(rgb=camera_from_info(msg, f"{self.name} {topic}"))
        raise SourceLostError(f"no sensor_msgs/CameraInfo on {topic} within {self.options.stall_s:g} s "
                         "(is the robot publishing? name the topic with --camera-info-topic, or give "
                         "--calibration)")

    def events(self) -> Iterator[SourceEvent]:
        """Frames and odometry as they arrive, until ``stop``.

        Raises:
            SourceLostError: no colour image for ``stall_s`` seconds.
        """
        pairer = FramePairer(self.cfg, self.calibration, self.name)
        self.skipped = pairer.skipped
        try:
            for role, msgtype, msg in self._messages(self.options.stall_s):
                if role == "odom":
                    yield odometry_sample(msg)
                elif role != "info":
                    yield from pairer.add(role == "rgb", msg, msgtype)
            if not self._stop.is_set():
                raise SourceLostError(f"no images on {self.cfg.rgb_topic} for {self.options.stall_s:g} s")
        finally:
            self.close()


def ros2_connector(config: BagSourceConfig, options: Ros2Options) -> Connector:
    """A connector (:class:`~wardmap.edge.live.ReconnectingSource`) subscribing to a robot's topics."""

    def connect(stop: threading.Event) -> Ros2Source:
        return Ros2Source(config, options, stop)

    return connect

