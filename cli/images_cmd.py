"""``wardmap images erase``: erase the stored keyframe images of a time range (an erase order).

The images (colour JPEG, thermal raster) of every keyframe captured in ``[--from, --to)``
(optionally of one robot) are erased in the server's store; poses, features, the pose graph
and the object map stay (``SqliteMapStore.erase_images``). Works while the server runs; the
REST image route answers 410 for an erased image.
"""

from __future__ import annotations

import argparse
from datetime import datetime

from wardmap.cli.db_options import db_password
from wardmap.cli.store_args import add_db_arg, check_existing_store
from wardmap.shared.errors import ConfigError


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("images", help="erase stored keyframe images of a time range", description=__doc__)
    actions = p.add_subparsers(dest="action", metavar="ACTION")
    actions.required = True
    erase = actions.add_parser("erase", help="erase the images of keyframes captured in [--from, --to)")
    add_db_arg(erase)
    erase.add_argument("--from", dest="start", required=True, metavar="ISO",
                       help="first capture time, ISO 8601 with a zone, e.g. 2026-11-26T10:00:00Z")
    erase.add_argument("--to", dest="end", required=True, metavar="ISO", help="end of the range (excluded)")
    erase.add_argument("--robot", metavar="ID", help="only this robot's keyframes")
    p.set_defaults(func=run)


def parse_instant(text: str, flag: str) -> float:
    """An ISO 8601 time with a zone (``Z`` or ``+01:00``) as POSIX seconds; ConfigError otherwise."""
    try:
        when = datetime.fromisoformat(text)
    except ValueError:
        raise ConfigError(f"bad {flag} {text!r}: expected ISO 8601, e.g. 2026-11-26T10:00:00Z") from None
    if when.tzinfo is None:
        raise ConfigError(f"bad {flag} {text!r}: give a time zone (Z or +HH:MM), the store keeps UTC seconds")
    return when.timestamp()


def run(args: argparse.Namespace) -> int:
    from wardmap.server.retention import erase_range
    from wardmap.server.store import open_store

    start, end = parse_instant(args.start, "--from"), parse_instant(args.end, "--to")
    if not start < end:
        raise ConfigError(f"--from {args.start} must be before --to {args.end}")
    check_existing_store(args.db)
    with open_store(args.db, password=db_password(args)) as store:
        n = erase_range(store, start, end, robot_id=args.robot)
    print(f"erased the images of {n} keyframes captured in [{args.start}, {args.end})"
          + (f" by {args.robot}" if args.robot else ""), flush=True)
    return 0
