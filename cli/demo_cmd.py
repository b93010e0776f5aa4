"""``wardmap demo``: router + map server + N simulated robots on loopback (see :mod:`wardmap.tools.demo`)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "demo",
        help="router + map server + simulated robots on loopback",
        description="Simulate N robots, run a Zenoh router, the map server and one edge agent per robot "
        "as subprocesses on loopback, print a summary (keyframes produced vs delivered, ATE, bytes per "
        "keyframe), then keep router and server running until Ctrl-C (or stop at once with --exit).",
    )
    p.add_argument("--robots", type=int, default=2, metavar="N", help="number of robots, 1..4 (default: 2)")
    p.add_argument("--duration", type=float, default=30.0, metavar="S",
                   help="seconds of camera per robot, at 10 Hz (default: 30)")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="simulator seed (default: 0)")
    p.add_argument("--exit", action="store_true", help="stop everything after the summary")
    p.add_argument("--http", default="127.0.0.1:8080", metavar="HOST:PORT",
                   help="map server REST address; a free port is used if it is busy (default: %(default)s)")
    p.add_argument("--map-poses", action="store_true",
                   help="start each robot at its ground-truth map pose (--map-pose) instead of letting the "
                        "server anchor it by place recognition")
    p.add_argument("--keep", type=Path, metavar="DIR",
                   help="work in DIR (new or empty) and keep it: data sets, outboxes, map.db, logs")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.cli.server_cmd import parse_http
    from wardmap.tools.demo import DemoOptions, run_demo

    host, port = parse_http(args.http)
    opts = DemoOptions(robots=args.robots, duration_s=args.duration, seed=args.seed, exit_after=args.exit,
                       http_host=host, http_port=port, keep=args.keep, map_poses=args.map_poses)
    return run_demo(opts)
