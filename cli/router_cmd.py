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
        metavar="tcp/HOST:PORT",
        help="endpoint to listen on (repeatable; required unless --check), e.g. tcp/0.0.0.0:7447",
    )
    p.add_argument(
        "--check",
        metavar="tcp/HOST:PORT",
        help="health check: exit 0 if a zenoh router answers at this endpoint, else 1 (runs no router)",
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
    from wardmap.server.router import check_router, run_router
    from wardmap.shared.errors import ConfigError
    from wardmap.shared.sdnotify import notify

    if args.check is not None:
        if args.listen:
            raise ConfigError("--check runs no router: give it without --listen")
        print(f"zenoh router {check_router(args.check)} at {args.check}", flush=True)
        return 0
    if not args.listen:
        raise ConfigError("wardmap router needs --listen tcp/HOST:PORT (or --check tcp/HOST:PORT)")

    def ready(endpoints: list[str]) -> None:
        print(f"router listening on {' '.join(endpoints)}", flush=True)
        notify("READY=1")

    run_router(args.listen, config_file=args.config, on_ready=ready)
    return 0
