"""``wardmap router``: run a Zenoh router that robots and map servers connect to."""

from __future__ import annotations

import argparse
from pathlib import Path

from wardmap.cli.logopts import add_log_format


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("router", help="run a Zenoh router", description=__doc__)
    p.add_argument(
        "--listen",
        action="append",
        required=True,
        metavar="tcp/HOST:PORT",
        help="endpoint to listen on (repeatable), e.g. tcp/0.0.0.0:7447",
    )
    p.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="zenoh config file (.json5/.json/.yaml); --listen and wardmap defaults override it",
    )
    add_log_format(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.server.router import run_router

    def ready(endpoints: list[str]) -> None:
        print(f"router listening on {' '.join(endpoints)}", flush=True)

    run_router(args.listen, config_file=args.config, on_ready=ready)
    return 0
