"""``wardmap export``: write the object map as GeoJSON (with robot paths) or PLY (with a point cloud)."""

from __future__ import annotations

import argparse
import json

from wardmap.cli.progress import Progress


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "export",
        help="write the object map and robot paths as GeoJSON",
        description="Export a server database (sqlite:///PATH or postgresql://...: objects and each "
        "robot's map trajectory) or a `wardmap map` output (its folder or landmarks.json: the landmarks) "
        "to a file. GeoJSON coordinates are map-frame metres, not longitude/latitude (docs/web.md). "
        "The last line on stdout is a JSON summary.",
    )
    p.add_argument("source", metavar="SOURCE",
                   help="a server's database (sqlite:///PATH, or postgresql://USER@HOST:PORT/DB with "
                        "the password in $WARDMAP_DB_PASSWORD or ~/.pgpass), or a `wardmap map` output")
    p.add_argument(
        "--format", choices=("geojson", "ply", "rrd"), default="geojson",
        help="geojson (default): objects and map trajectories; ply: object boxes and the keyframes' "
        "depth as a coloured point cloud (extra `export`); rrd: a Rerun recording of keyframes, paths "
        "and objects over time (extra `rerun`)",
    )
    p.add_argument("--out", required=True, metavar="FILE", help="the file to write (replaced)")
    p.add_argument(
        "--include-unconfirmed", action="store_true", help="also objects association has not confirmed"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.tools.export import export

    with Progress("keyframes") as bar:
        summary = export(args.source, args.out, fmt=args.format, include_unconfirmed=args.include_unconfirmed,
                         progress=bar.update)
    print(json.dumps({"out": args.out, **summary}), flush=True)
    return 0
