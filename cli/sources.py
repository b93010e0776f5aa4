"""Frame sources named on the command line: a data-set folder, ``bag:PATH``, ``sim:SCENARIO``,
a camera (``realsense[:SERIAL]``, ``orbbec[:N]``) or live ROS 2 topics (``ros2:[ENDPOINT]``),
optionally with a UVC thermal camera (``--thermal INDEX``). Cameras and ROS 2 topics are live:
they reconnect when they go away (:class:`~wardmap.edge.live.ReconnectingSource`).

The composition root of sources (``wardmap track`` and ``wardmap edge`` share it): the
simulator's live run is built here because the edge never imports the simulator.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from wardmap.edge.bag import BagSourceConfig
    from wardmap.edge.stream import StreamSource
    from wardmap.shared.dataset import Calibration

SOURCE_METAVAR = "DATASET|bag:PATH|sim:SCENARIO[:SEED[:ROBOT]]|realsense[:SERIAL]|orbbec[:N]|ros2:[ENDPOINT]"
SOURCE_HELP = ("data-set folder, a ROS 1/ROS 2/MCAP recording (bag:PATH; topics by the options below "
               "or the config's [source] table), a simulated robot rendered live "
               "(e.g. sim:aisle_slow_1, sim:two_robots:0:robot_1), a RealSense camera "
               "(realsense, realsense:SERIAL; extra 'realsense'), an Orbbec camera (orbbec, orbbec:N; "
               "pyorbbecsdk2, docs/sources.md) or a ROS 2 robot's live topics over "
               "Zenoh (ros2: for rmw_zenoh's router at tcp/127.0.0.1:7447, ros2:tcp/HOST:PORT)")
NOT_AVAILABLE = {  # --source prefix -> why not
    "k4a": "pyk4a needs Microsoft's Azure Kinect SDK (libk4a), which has no Linux package here; record "
           "with the Azure Kinect ROS driver and use bag:PATH or ros2:",
}
LIVE = ("realsense", "orbbec", "ros2")

_FLAGS = {  # option -> BagSourceConfig field
    "rgb_topic": "colour Image or CompressedImage topic",
    "depth_topic": "depth Image topic registered to the colour camera (16UC1 mm or 32FC1 m)",
    "camera_info_topic": "the colour camera's CameraInfo topic",
    "odom_topic": "nav_msgs/Odometry topic ('' for none; default /odom when recorded)",
    "calibration": "calibration.toml replacing the recording's CameraInfo and tf (a camera: "
                   "its [base] mount and [thermal] camera)",
}


def add_bag_options(p: argparse.ArgumentParser) -> None:
    """The ``bag:PATH`` options (each overrides the config's ``[source]`` table)."""
    g = p.add_argument_group("ROS recordings and topics (bag:PATH, ros2:), cameras")
    for name, text in _FLAGS.items():
        metavar = "TOPIC" if "topic" in name else "FILE"
        g.add_argument("--" + name.replace("_", "-"), dest=name, metavar=metavar, help=text)
    g.add_argument("--thermal", type=int, metavar="INDEX",
                   help="a UVC thermal camera (/dev/videoINDEX, 16-bit Y16, e.g. a Lepton on a "
                   "PureThermal board) beside the colour camera; needs --calibration with [thermal]")


def add_associations_option(p: argparse.ArgumentParser) -> None:
    """``--associations FILE``: the rgb/depth association file of a data-set folder."""
    p.add_argument(
        "--associations", metavar="FILE",
        help="rgb/depth association file of a data-set folder (TUM associate.py output; default: the "
        "folder's associations.txt, rgbd_assoc.txt or assoc.txt, else nearest stamps)",
    )


def add_source_options(p: argparse.ArgumentParser) -> None:
    """The options of a command that opens a source: ``--associations`` and the bag options."""
    add_associations_option(p)
    add_bag_options(p)


def readout_line(calibration: Calibration) -> str:
    """One line saying which rolling-shutter readout time tracking uses, and why."""
    model = calibration.readout
    return f"rolling-shutter readout: {1e3 * model.readout_s:.1f} ms ({model.source})"


def bag_config(args: argparse.Namespace, config_path: str | None) -> BagSourceConfig:
    """The ``[source]`` table of ``config_path`` with the command line's bag options applied."""
    from wardmap.edge.bag import BagSourceConfig
    from wardmap.shared.config import load_config

    cfg = load_config(BagSourceConfig, config_path, section="source")
    overrides: dict[str, Any] = {k: getattr(args, k) for k in _FLAGS if getattr(args, k, None) is not None}
    return dataclasses.replace(cfg, **overrides)


def open_source(spec: str, args: argparse.Namespace, config_path: str | None) -> StreamSource:
    """The source ``spec`` names (see the module docstring).

    Raises:
        DatasetError: a folder or recording that cannot be read, a topic that does not exist.
        SimulationError: an unknown scenario or robot.
    """
    from wardmap.edge.bag import BagSource, is_bag_source
    from wardmap.edge.stream import FrameSourceStream
    from wardmap.shared.dataset import DatasetReader
    from wardmap.shared.errors import ConfigError, DatasetError

    associations = getattr(args, "associations", None)
    kind = spec.split(":", 1)[0]
    if associations is not None and (kind in (*NOT_AVAILABLE, *LIVE, "sim")
                                     or is_bag_source(spec)):
        raise DatasetError("--associations is for a data-set folder, not a recording, a camera or a "
                           "simulated robot")
    source: StreamSource
    if kind in NOT_AVAILABLE:
        raise ConfigError(f"--source {kind} is not available: {NOT_AVAILABLE[kind]}")
    if kind in LIVE:
        source = _live_source(kind, spec, args, config_path)
    elif spec.startswith("sim:"):
        from wardmap.sim.live import LiveRun, SimSource

        sim = SimSource.parse(spec)
        source = FrameSourceStream(LiveRun(sim.scenario, sim.seed, sim.robot))
    elif is_bag_source(spec):
        path = spec.removeprefix("bag:")
        if not path:
            raise DatasetError("bag: needs a path, e.g. bag:recording.mcap or bag:rosbag2_folder")
        source = BagSource(path, bag_config(args, config_path))
    elif not Path(spec).is_dir():
        raise DatasetError(f"data set {spec!r} is not a folder (a recording is bag:PATH, a simulated "
                           "robot sim:SCENARIO, a camera realsense[:SERIAL] or orbbec[:N], ROS 2 topics "
                           "ros2:)")
    else:
        source = FrameSourceStream(DatasetReader(spec, associations=associations))
    if getattr(args, "thermal", None) is not None:
        source = _with_thermal(source, args.thermal, bag_config(args, config_path).calibration)
    return source


def _live_source(kind: str, spec: str, args: argparse.Namespace, config_path: str | None) -> StreamSource:
    """A camera or ROS 2 topics behind the reconnect loop (first connect now: errors are one line)."""
    from wardmap.edge.live import ReconnectingSource
    from wardmap.shared.dataset import load_calibration

    cfg = bag_config(args, config_path)
    if kind == "realsense":
        from wardmap.edge.realsense import parse_spec, realsense_connector

        calib = load_calibration(cfg.calibration) if cfg.calibration else None
        return ReconnectingSource(realsense_connector(parse_spec(spec), calibration=calib))
    if kind == "orbbec":
        from wardmap.edge import orbbec

        calib = load_calibration(cfg.calibration) if cfg.calibration else None
        return ReconnectingSource(orbbec.orbbec_connector(orbbec.parse_spec(spec), calibration=calib))
    from wardmap.edge import ros2live

    return ReconnectingSource(ros2live.ros2_connector(cfg, ros2live.parse_spec(spec, cfg)))


def _with_thermal(source: StreamSource, index: int, calibration_path: str) -> StreamSource:
    from wardmap.edge.thermal import ThermalCapture, WithThermal
    from wardmap.shared.dataset import load_calibration
    from wardmap.shared.errors import ConfigError

    if not calibration_path:
        raise ConfigError("--thermal needs --calibration FILE with a [thermal] table (the thermal camera "
                          "and T_rgb_thermal)")
    calib = load_calibration(calibration_path)
    if calib.thermal is None:
        raise ConfigError(f"--thermal: {calibration_path} has no [thermal] table (the thermal camera and "
                          "T_rgb_thermal)")
    capture = ThermalCapture(index, (calib.thermal.width, calib.thermal.height))
    return WithThermal(source, capture, calib)
