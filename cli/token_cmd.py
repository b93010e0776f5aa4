"""``wardmap token``: create, list and revoke the REST API's bearer tokens (``server/tokens.py``).

The token text is printed once, by ``create``, and never stored (the store keeps its SHA-256
digest). Works on the server's database while the server runs: a new or revoked token counts
from the next request on.
"""

from __future__ import annotations

import argparse
import time

from wardmap.cli.db_options import db_password
from wardmap.cli.store_args import add_db_arg, check_existing_store


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("token", help="create, list or revoke REST API tokens", description=__doc__)
    actions = p.add_subparsers(dest="action", metavar="ACTION")
    actions.required = True
    create = actions.add_parser("create", help="create a token and print it (once)")
    create.add_argument("--scope", required=True, choices=("read", "admin"),
                        help="read: every read route; admin: also the routes that change state")
    create.add_argument("--name", default="", help="what the token is for (shown by list)")
    listing = actions.add_parser("list", help="list tokens (ids, scopes, names; never secrets)")
    revoke = actions.add_parser("revoke", help="revoke a token by its id")
    revoke.add_argument("token_id", metavar="ID", help="the id from `wardmap token list`")
    for q in (create, listing, revoke):
        add_db_arg(q)
    p.set_defaults(func=run)


def _when(s: float | None) -> str:
    return "-" if s is None else time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(s))


def run(args: argparse.Namespace) -> int:
    from wardmap.server.store import open_store
    from wardmap.server.tokens import TokenError, create_token, revoke_token

    check_existing_store(args.db, TokenError)
    with open_store(args.db, password=db_password(args)) as store:
        if args.action == "create":
            issued = create_token(store, args.scope, args.name)
            print(issued.text, flush=True)
        elif args.action == "revoke":
            revoke_token(store, args.token_id)
            print(f"revoked {args.token_id}")
        else:
            print(f"{'id':<12}  {'scope':<5}  {'created':<20}  {'revoked':<20}  name")
            for t in store.tokens():
                when = f"{_when(t.created_s):<20}  {_when(t.revoked_s):<20}"
                print(f"{t.token_id:<12}  {t.scope:<5}  {when}  {t.name}")
    return 0
