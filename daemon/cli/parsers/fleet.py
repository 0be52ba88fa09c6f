"""The arguments of `rumba fleet`; the command is ``daemon.cli.commands.fleet``."""

from __future__ import annotations

import argparse
from pathlib import Path


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.fleet import cmd_fleet

    return cmd_fleet(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fleet", help="serve the read-only fleet page over the fleet store")
    p.add_argument("--store", required=True, metavar="URL",
                   help="postgresql://user@host/db?passfile=… (the daemons' store.url)")
    p.add_argument("--listen", default="127.0.0.1:8090", metavar="HOST:PORT",
                   help="address to serve on (default 127.0.0.1:8090; port 0: any free)")
    p.add_argument("--token-file", required=True, type=Path,
                   help="file with the access token (mode 600, ≥ 16 characters)")
    p.add_argument("--stale-after-h", type=float, default=26.0,
                   help="flag a machine whose last verdict is older (hours, default 26)")
    p.add_argument("--reports-dir", action="append", type=Path, default=[],
                   help="directory the page may serve reports from (repeatable)")
    p.add_argument("--state-dir", type=Path,
                   help="keeps the session secret so sign-ins survive a restart")
    p.add_argument("--tls-cert", type=Path, help="PEM certificate (with --tls-key)")
    p.add_argument("--tls-key", type=Path, help="PEM private key, mode 600")
    p.add_argument("--public-origin", action="append", default=[],
                   help="scheme://name[:port] users type, besides the listen address")
    p.add_argument("--opcua", type=Path, metavar="YAML",
                   help="also serve every machine's results over OPC UA: a file "
                        "with the keys of daemon.yaml's opcua_server section")
    p.add_argument("--opcua-poll-s", type=float, default=5.0,
                   help="how often the OPC UA server looks for finished runs (default 5 s)")
    p.set_defaults(func=_run)
