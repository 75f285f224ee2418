"""``rra certs PKG --out DIR``: the system CA and the certificates of every host and role.

Hosts come from the package's system model (`rra_agent.security.acl.system_hosts`; a model
naming none has the one host ``local``) plus ``--host``. Re-running on the same folder
reuses the CA and writes only what is missing, stale or about to expire.
"""

from __future__ import annotations

import argparse

from rra_agent.security.certs import DEFAULT_DAYS, issue, parse_san


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("package", metavar="PKG", help="system package folder (or its rra.yaml)")
    p.add_argument("--out", required=True, metavar="DIR", help="certificate folder")
    p.add_argument(
        "--san",
        action="append",
        default=[],
        metavar="HOST=ADDR[,ADDR...]",
        help="addresses other hosts use to reach HOST's router (IPs or DNS names)",
    )
    p.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="NAME",
        help="also make certificates for this host (e.g. `rra up --host NAME`)",
    )
    p.add_argument(
        "--days", type=int, default=DEFAULT_DAYS, help=f"validity (default {DEFAULT_DAYS})"
    )


def run(args: argparse.Namespace) -> int:
    from rra_agent.deployment import deploy
    from rra_agent.security.acl import system_hosts

    dep = deploy(args.package)
    hosts = sorted({*system_hosts(dep), *args.host})
    sans: dict[str, list[str]] = {}
    for text in args.san:
        host, addrs = parse_san(text)
        sans.setdefault(host, []).extend(addrs)
    done = issue(args.out, hosts, sans=sans, days=args.days, ca_name=f"rra {dep.system} CA")
    for item in done:
        print(item.line())
    changed = sum(item.action != "kept" for item in done)
    print(
        f"{changed} file(s) written for system {dep.system!r}, hosts {', '.join(hosts)}.\n"
        f"Copy {args.out}/<host> to each host (--certs DIR/<host> for `rra up`/`rra agent`), "
        f"{args.out}/operator to the operators (--certs for the tools); "
        f"{args.out}/ca/ca.key stays here."
    )
    return 0
