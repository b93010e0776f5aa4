"""``--db-password-file``: the PostgreSQL password of every command that takes ``--db``.

The password is never an argument (a command line is visible to every user of the machine):
it comes from this file, else the ``WARDMAP_DB_PASSWORD`` environment variable, else libpq's
``PGPASSFILE``/``~/.pgpass`` (``server/store/postgres.py``). SQLite URLs ignore it.
"""

from __future__ import annotations

import argparse


def add_password_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--db-password-file", metavar="FILE",
        help="PostgreSQL password: the first line of FILE (else $WARDMAP_DB_PASSWORD, else ~/.pgpass); "
             "a password in the --db URL is refused",
    )


def db_password(args: argparse.Namespace) -> str | None:
    """The password from ``--db-password-file`` (None when not given); StoreError if unreadable."""
    if args.db_password_file is None:
        return None
    from wardmap.server.store import read_password_file

    return read_password_file(args.db_password_file)
