"""Frame sources named on the command line: a data-set folder, ``bag:PATH`` or ``sim:SCENARIO``.

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

SOURCE_METAVAR = "DATASET|bag:PATH|sim:SCENARIO[:SEED[:ROBOT]]"
SOURCE_HELP = ("data-set folder, a ROS 1/ROS 2/MCAP recording (bag:PATH; topics by the options below "
               "or the config's [source] table), or a simulated robot rendered live "
               "(e.g. sim:aisle_slow_1, sim:two_robots:0:robot_1)")

_FLAGS = {  # option -> BagSourceConfig field
    "rgb_topic": "colour Image or CompressedImage topic",
    "depth_topic": "depth Image topic registered to the colour camera (16UC1 mm or 32FC1 m)",
    "camera_info_topic": "the colour camera's CameraInfo topic",
    "odom_topic": "nav_msgs/Odometry topic ('' for none; default /odom when recorded)",
    "calibration": "calibration.toml replacing the recording's CameraInfo and tf",
}


def add_bag_options(p: argparse.ArgumentParser) -> None:
    """The ``bag:PATH`` options (each overrides the config's ``[source]`` table)."""
    g = p.add_argument_group("ROS recordings (bag:PATH)")
    for name, text in _FLAGS.items():
        metavar = "TOPIC" if "topic" in name else "FILE"
        g.add_argument("--" + name.replace("_", "-"), dest=name, metavar=metavar, help=text)


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
    from wardmap.shared.errors import DatasetError

    associations = getattr(args, "associations", None)
    if associations is not None and (spec.startswith("sim:") or is_bag_source(spec)):
        raise DatasetError("--associations is for a data-set folder, not a recording or a simulated robot")
    if spec.startswith("sim:"):
        from wardmap.sim.live import LiveRun, SimSource

        sim = SimSource.parse(spec)
        return FrameSourceStream(LiveRun(sim.scenario, sim.seed, sim.robot))
    if is_bag_source(spec):
        path = spec.removeprefix("bag:")
        if not path:
            raise DatasetError("bag: needs a path, e.g. bag:recording.mcap or bag:rosbag2_folder")
        return BagSource(path, bag_config(args, config_path))
    if not Path(spec).is_dir():
        raise DatasetError(f"data set {spec!r} is not a folder (a recording is bag:PATH, a simulated "
                           "robot sim:SCENARIO)")
    return FrameSourceStream(DatasetReader(spec, associations=associations))
