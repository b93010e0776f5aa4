"""``wardmap edge``: run one robot's edge agent (tracker -> outbox -> Zenoh)."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

from wardmap.cli.logopts import add_log_format
from wardmap.cli.sources import SOURCE_HELP, SOURCE_METAVAR, add_source_options, open_source, readout_line
from wardmap.cli.zenoh_args import add_zenoh_args, zenoh_options

OUTBOX_FILE = "outbox.sqlite"
"""Name of the outbox file inside ``--outbox DIR``."""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "edge",
        help="run one robot: track a camera, ROS 2 topics, a recording or a simulated robot and send "
        "keyframes to the map server",
        description="Track a live source (a RealSense camera, a ROS 2 robot's topics over Zenoh), a "
        "data-set folder, a recording or a robot the simulator renders live with the edge "
        "frontend and send every keyframe over "
        "Zenoh through a durable outbox (re-sent until the server acks it). A live source runs until "
        "stopped and reconnects when it goes away. Prints one ready line, "
        "then a JSON summary line at the end. SIGTERM/Ctrl-C stop tracking and flush.",
    )
    p.add_argument("--robot", required=True, metavar="ID", help="robot id, 1-64 of [A-Za-z0-9_.-]")
    p.add_argument("--source", required=True, metavar=SOURCE_METAVAR, help=SOURCE_HELP)
    p.add_argument(
        "--connect", action="append", required=True, metavar="tcp|tls|quic/HOST:PORT",
        help="router endpoint (repeat)",
    )
    p.add_argument("--outbox", required=True, type=Path, metavar="DIR", help=f"outbox folder ({OUTBOX_FILE})")
    p.add_argument("--rate", type=float, metavar="HZ", help="frames per second (0 = as fast as possible)")
    p.add_argument("--drop-when-behind", action="store_true", default=None,
                   help="replay like a camera: drop (and count) frames tracking cannot keep up with")
    p.add_argument("--max-frames", type=int, metavar="K", help="stop after K frames")
    p.add_argument("--record", type=Path, metavar="DIR",
                   help="also write every frame and odometry sample the source gives to this new "
                   "data-set folder (replay it with wardmap track DIR)")
    p.add_argument("--labels", metavar="none|oracle|onnx:PATH",
                   help="label source for dynamic-point removal and for finding people to redact")
    p.add_argument("--privacy", choices=("blank", "blur", "off"),
                   help="what is done to people in keyframe images before they leave the robot "
                   "(default: [agent] privacy, blank); blank and blur need --labels")
    p.add_argument(
        "--map-pose", metavar="X,Y,YAW_DEG",
        help="the robot's start pose on the shared map (metres, degrees), e.g. its dock; "
        "lets the server put this session's objects on the map",
    )
    p.add_argument("--config", metavar="FILE",
                   help="TOML file with [tracker], [agent], [source] and [zenoh] tables")
    p.add_argument(
        "--metrics-port", type=int, metavar="N",
        help="serve the agent's Prometheus metrics at http://HOST:N/metrics (off by default)",
    )
    p.add_argument(
        "--metrics-host", default="0.0.0.0", metavar="HOST",
        help="address of --metrics-port (default: %(default)s, for a Prometheus off the robot)",
    )
    add_log_format(p)
    add_source_options(p)
    add_zenoh_args(p)
    p.set_defaults(func=run)


def parse_map_pose(text: str) -> Any:
    """``X,Y,YAW_DEG`` -> (4, 4) planar pose; ConfigError naming the flag otherwise."""
    import math

    from wardmap.shared.errors import ConfigError
    from wardmap.shared.se3 import yaw_transform

    parts = text.split(",")
    try:
        x, y, yaw_deg = (float(v) for v in parts)
    except ValueError:
        raise ConfigError(f"bad --map-pose {text!r}: expected X,Y,YAW_DEG, e.g. 2.5,1.0,90") from None
    if not all(math.isfinite(v) for v in (x, y, yaw_deg)):
        raise ConfigError(f"bad --map-pose {text!r}: values must be finite")
    return yaw_transform(x, y, math.radians(yaw_deg))


def _privacy_words(mode: str) -> str:
    """The ready line's privacy clause: loud when images leave unredacted."""
    return {"off": "NOT REDACTED (privacy off)", "blank": "blanked", "blur": "blurred"}[mode]


def run(args: argparse.Namespace) -> int:
    source = open_source(args.source, args, args.config)
    with contextlib.ExitStack() as stack:
        stack.callback(_close, source)
        return _run(args, source, stack)


def _close(source: Any) -> None:
    """Release a live source's device or session even if it was never streamed (idempotent)."""
    close = getattr(source, "close", None)
    if callable(close):
        close()


def _labels_words(labels: str) -> str:
    """The ready line's label clause: loud when nothing finds people and moving things."""
    if labels == "none":
        return "labels: NONE (points on people stay in the map)"
    return f"labels: {labels}"


def _run(args: argparse.Namespace, source: Any, stack: contextlib.ExitStack) -> int:
    from wardmap.edge.agent import AgentConfig, EdgeAgent, run_agent
    from wardmap.edge.live import RecordingSource
    from wardmap.edge.metrics import EdgeMetrics
    from wardmap.edge.tracker import TrackerConfig
    from wardmap.shared.config import load_config
    from wardmap.shared.sdnotify import notify

    tracker_cfg = load_config(TrackerConfig, args.config, section="tracker")
    agent_cfg = load_config(AgentConfig, args.config, section="agent")
    options = zenoh_options(args, args.config)
    overrides: dict[str, Any] = {}  # field name -> value; dataclasses.replace re-validates
    if args.rate is not None:
        overrides["rate_hz"] = args.rate
    if args.max_frames is not None:
        overrides["max_frames"] = args.max_frames
    if args.drop_when_behind is not None:
        overrides["drop_when_behind"] = True
    if args.labels is not None:
        overrides["labels"] = args.labels
    if args.privacy is not None:
        overrides["privacy"] = args.privacy
    agent_cfg = dataclasses.replace(agent_cfg, **overrides)  # re-validated by __post_init__
    if args.record is not None:
        source = RecordingSource(source, args.record)
    T_map_odom = None if args.map_pose is None else parse_map_pose(args.map_pose)
    metrics = None if args.metrics_port is None else EdgeMetrics(args.robot)
    agent = EdgeAgent(
        args.robot,
        source,
        args.connect,
        args.outbox / OUTBOX_FILE,
        config=agent_cfg,
        tracker_config=tracker_cfg,
        T_map_odom=T_map_odom,
        metrics=metrics,
        zenoh_options=options,
    )

    def ready(session_id: str, pending: int) -> None:
        print(
            f"edge {args.robot} ready: session {session_id}, connected to {' '.join(args.connect)}, "
            f"{pending} keyframes pending in {args.outbox / OUTBOX_FILE}, "
            f"source {source.name}, {_labels_words(agent_cfg.labels)}, "
            f"people in images: {_privacy_words(agent_cfg.privacy)}",
            flush=True,
        )
        print(f"edge {args.robot} {readout_line(source.calibration)}", file=sys.stderr, flush=True)
        if agent_cfg.labels == "none":
            print(f"edge {args.robot} warning: no label source (--labels): points on people and other "
                  "moving things go into the map", file=sys.stderr, flush=True)
        notify("READY=1")

    if metrics is not None:
        url = stack.enter_context(metrics.serve(args.metrics_port, args.metrics_host))
        print(f"edge {args.robot} metrics: {url}/metrics", file=sys.stderr, flush=True)
    summary = run_agent(agent, ready)
    if isinstance(source, RecordingSource):
        summary["recorded"] = {"folder": str(source.out), "frames": source.recorded,
                               "skipped": source.skipped}
    print(json.dumps(summary), flush=True)
    return 0
