"""``wardmap`` console script: one parser, one subcommand module per command.

Every subcommand translates :class:`WardmapError` into one line on stderr and exit
code 1; a Ctrl-C exits 130. Tracebacks appear only with ``-vv``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version

from wardmap.cli import (
    certs_cmd,
    dataset_cmd,
    demo_cmd,
    edge_cmd,
    eval_cmd,
    export_cmd,
    images_cmd,
    map_cmd,
    readout_cmd,
    router_cmd,
    segment_cmd,
    server_cmd,
    sim_cmd,
    token_cmd,
    track_cmd,
    train_seg_cmd,
    vocab_cmd,
)
from wardmap.shared.errors import WardmapError
from wardmap.shared.logsetup import configure_logging

log = logging.getLogger("wardmap")


def _version() -> str:
    try:
        return version("wardmap")
    except PackageNotFoundError:  # running from a source tree that is not installed
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="wardmap",
        description="Semantic SLAM for hospital service robots.",
    )
    parser.add_argument("--version", action="version", version=f"wardmap {_version()}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-v info, -vv debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    sim_cmd.register(sub)
    dataset_cmd.register(sub)
    track_cmd.register(sub)
    readout_cmd.register(sub)
    map_cmd.register(sub)
    segment_cmd.register(sub)
    train_seg_cmd.register(sub)
    eval_cmd.register(sub)
    router_cmd.register(sub)
    server_cmd.register(sub)
    token_cmd.register(sub)
    images_cmd.register(sub)
    certs_cmd.register(sub)
    edge_cmd.register(sub)
    demo_cmd.register(sub)
    export_cmd.register(sub)
    vocab_cmd.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose, log_format=getattr(args, "log_format", "text"))
    try:
        rc = args.func(args)
    except WardmapError as exc:
        print(f"wardmap {args.command}: error: {exc}", file=sys.stderr)
        if args.verbose >= 2:
            raise
        return 1
    except KeyboardInterrupt:
        print(f"wardmap {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
