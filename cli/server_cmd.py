"""``wardmap server``: run the map server (keyframe ingest from Zenoh + REST API)."""

from __future__ import annotations

import argparse

from wardmap.cli.db_options import add_password_option, db_password
from wardmap.cli.logopts import add_log_format
from wardmap.cli.zenoh_args import add_zenoh_args, zenoh_options
from wardmap.shared.errors import ConfigError


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("server", help="run the map server", description=__doc__)
    p.add_argument(
        "--connect",
        action="append",
        required=True,
        metavar="tcp|tls|quic/HOST:PORT",
        help="zenoh router endpoint to connect to (repeatable), e.g. tcp/127.0.0.1:7447",
    )
    p.add_argument(
        "--db", default="sqlite:///wardmap.db", metavar="URL",
        help="keyframe store: sqlite:///PATH or postgresql://USER@HOST:PORT/DB (default: %(default)s)",
    )
    add_password_option(p)
    p.add_argument(
        "--http", default="127.0.0.1:8080", metavar="HOST:PORT",
        help="REST API address (default: %(default)s)",
    )
    p.add_argument(
        "--config", metavar="FILE",
        help="TOML file with [pipeline], [perception], [association] and [zenoh] tables "
             "(deploy/server.toml)",
    )
    p.add_argument(
        "--insecure-loopback", action="store_true",
        help="serve the REST API without tokens; refused unless --http is a loopback address "
             "(demo and tests; create tokens with `wardmap token create`)",
    )
    p.add_argument(
        "--name", metavar="NAME",
        help="this server's name among several on one database (the writer lease's holder runs the "
             "mapping stage; /readyz and /metrics show it); default: HOST-PID",
    )
    p.add_argument(
        "--perception-workers", type=int, metavar="N",
        help="perception worker processes on this server, writer or standby (overrides [mapping] "
             "perception_workers; 0: the writer's mapping stage measures every keyframe itself)",
    )
    add_log_format(p)
    add_zenoh_args(p)
    p.set_defaults(func=run)


def parse_http(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[IPv6]:PORT`` allowed) as ``(host, port)``; ConfigError otherwise."""
    host, sep, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"bad --http {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8080")
    return host, int(port)


def run(args: argparse.Namespace) -> int:
    from wardmap.server.app import run_server
    from wardmap.shared.sdnotify import notify, start_watchdog

    host, port = parse_http(args.http)
    options = zenoh_options(args, args.config)

    def ready(url: str) -> None:
        print(f"server ready: {url}", flush=True)
        notify("READY=1")  # systemd Type=notify: store open, router connected, ingest subscribed
        start_watchdog(lambda: _answers(f"{url}/healthz"))  # WatchdogSec: the HTTP loop still serves

    run_server(args.connect, args.db, host, port, on_ready=ready, config_path=args.config,
               insecure_loopback=args.insecure_loopback, zenoh_options=options,
               db_password=db_password(args), name=args.name, perception_workers=args.perception_workers)
    return 0


def _answers(url: str) -> bool:
    """Whether ``GET url`` answers 200 within 5 s."""
    import urllib.request

    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return bool(r.status == 200)
    except OSError:
        return False
