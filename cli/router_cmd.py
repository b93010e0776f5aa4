"""``wardmap router``: run a Zenoh router that robots and map servers connect to.

With ``--listen tls/HOST:PORT`` (or ``quic/``), ``--tls-cert``/``--tls-key`` (the router's certificate) and
``--tls-ca`` (the site CA) it accepts only clients with a certificate of that CA; the ACL
that ``wardmap certs`` writes (``--zenoh-config DIR/acl.json5``) limits what each may do.
"""

from __future__ import annotations

import argparse

from wardmap.cli.logopts import add_log_format
from wardmap.cli.zenoh_args import add_zenoh_args, zenoh_options


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("router", help="run a Zenoh router", description=__doc__)
    p.add_argument(
        "--listen",
        action="append",
        metavar="tcp|tls|quic/HOST:PORT",
        help="endpoint to listen on (repeatable; required unless --check), e.g. tcp/0.0.0.0:7447 or "
        "tls/0.0.0.0:7447",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="tcp|tls|quic/HOST:PORT",
        help="another router to join into one mesh (repeatable; retried until it answers), so robots "
        "and servers on either router reach each other",
    )
    p.add_argument(
        "--check",
        metavar="tcp/HOST:PORT",
        help="health check: exit 0 if a zenoh router answers at this endpoint, else 1 (runs no router)",
    )
    add_zenoh_args(p)
    # The router's --config was always a zenoh config file: kept as an alias of --zenoh-config.
    p.add_argument("--config", dest="zenoh_config", metavar="FILE", help=argparse.SUPPRESS)
    add_log_format(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.server.router import check_router, run_router
    from wardmap.shared.errors import ConfigError
    from wardmap.shared.sdnotify import notify

    if args.check is not None:
        if args.listen or args.connect:
            raise ConfigError("--check runs no router: give it without --listen or --connect")
        print(f"zenoh router {check_router(args.check, zenoh_options(args))} at {args.check}", flush=True)
        return 0
    if not args.listen:
        raise ConfigError("wardmap router needs --listen tcp/HOST:PORT (or --check tcp/HOST:PORT)")

    def ready(endpoints: list[str]) -> None:
        print(f"router listening on {' '.join(endpoints)}", flush=True)
        notify("READY=1")

    run_router(args.listen, options=zenoh_options(args), on_ready=ready, connect=args.connect)
    return 0
