"""``wardmap router``: run a Zenoh router that robots and map servers connect to.

With ``--listen tls/HOST:PORT`` (or ``quic/``), ``--tls-cert``/``--tls-key`` (the router's certificate) and
``--tls-ca`` (the site CA) it accepts only clients with a certificate of that CA; the ACL
that ``wardmap certs`` writes (``--zenoh-config DIR/acl.json5``) limits what each may do.
"""

from __future__ import annotations

import argparse

from wardmap.cli.zenoh_args import add_zenoh_args, zenoh_options


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("router", help="run a Zenoh router", description=__doc__)
    p.add_argument(
        "--listen",
        action="append",
        required=True,
        metavar="tcp|tls|quic/HOST:PORT",
        help="endpoint to listen on (repeatable), e.g. tcp/0.0.0.0:7447 or tls/0.0.0.0:7447",
    )
    add_zenoh_args(p)
    # The router's --config was always a zenoh config file: kept as an alias of --zenoh-config.
    p.add_argument("--config", dest="zenoh_config", metavar="FILE", help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.server.router import run_router

    def ready(endpoints: list[str]) -> None:
        print(f"router listening on {' '.join(endpoints)}", flush=True)

    run_router(args.listen, options=zenoh_options(args), on_ready=ready)
    return 0
