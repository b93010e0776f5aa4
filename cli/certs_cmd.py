"""``wardmap certs``: a site CA, certificates for routers, servers and robots, and the router ACL.

  wardmap certs init --out DIR                       # DIR/ca.crt, DIR/ca.key
  wardmap certs issue router --role router --host 192.0.2.10 --out DIR
  wardmap certs issue server --role server --out DIR
  wardmap certs issue robot_0 --role robot --out DIR  # CN = the robot id
  wardmap certs acl --out DIR                        # rewrite DIR/acl.json5 (after removing one)

Each issue rewrites DIR/acl.json5 from the robot and server certificates in DIR; the router
loads it with --zenoh-config. Keys are written 0600 and no file is overwritten
(docs/security.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("certs", help="make a site CA, issue TLS certificates, write the router ACL",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = p.add_subparsers(dest="action", metavar="ACTION")
    actions.required = True
    init = actions.add_parser("init", help="create the site CA (ca.crt, ca.key)")
    issue = actions.add_parser("issue", help="issue NAME.crt and NAME.key signed by the site CA")
    issue.add_argument("name", metavar="NAME", help="common name: the robot id for a robot")
    issue.add_argument("--role", required=True, choices=("robot", "server", "router"))
    issue.add_argument("--host", action="append", default=[], metavar="HOST",
                       help="DNS name or IP address the certificate is valid for (repeatable); "
                            "a router needs the ones clients connect to")
    issue.add_argument("--days", type=int, default=825, metavar="N", help="validity (default: %(default)s)")
    acl = actions.add_parser("acl", help="rewrite acl.json5 from the certificates in --out")
    for q in (init, issue, acl):
        q.add_argument("--out", required=True, type=Path, metavar="DIR", help="the site's certificate folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.server.certs import fleet, init_ca, issue, write_acl

    if args.action == "init":
        cert = init_ca(args.out)
        print(f"wrote {cert} and {args.out / 'ca.key'} (keep the key secret: it signs certificates)")
    elif args.action == "issue":
        issued = issue(args.out, args.name, args.role, hosts=args.host, days=args.days)
        print(f"wrote {issued.cert} and {issued.key}")
        if issued.acl is not None:
            print(f"wrote {issued.acl}: {len(issued.robots)} robots, {len(issued.servers)} servers")
    else:
        path = write_acl(args.out)
        robots, servers = fleet(args.out)
        print(f"wrote {path}: {len(robots)} robots, {len(servers)} servers")
    return 0
