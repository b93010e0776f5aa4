"""The ``--db`` option of the commands that work on the map server's store (``token``, ``images``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from wardmap.shared.errors import ConfigError, WardmapError

DEFAULT_DB = "sqlite:///wardmap.db"


def add_db_arg(p: argparse.ArgumentParser) -> None:
    """``--db URL`` (default :data:`DEFAULT_DB`) and ``--db-password-file`` (``db_options.py``)."""
    from wardmap.cli.db_options import add_password_option

    p.add_argument("--db", default=DEFAULT_DB, metavar="URL",
                   help="the map server's store (default: %(default)s)")
    add_password_option(p)


def check_existing_store(url: str, error: type[WardmapError] = ConfigError) -> None:
    """Raise ``error`` when ``url`` names an SQLite file that does not exist: a mistyped path
    would make a new, empty store that no server serves."""
    from wardmap.server.store import SQLITE_SCHEME

    if url.startswith(SQLITE_SCHEME):
        path = Path(url[len(SQLITE_SCHEME):].partition("?")[0])
        if not path.is_file():
            raise error(f"no store at {path}: give the server's --db "
                        "(it creates the file at its first start)")
