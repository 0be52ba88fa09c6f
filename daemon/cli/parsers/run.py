"""The arguments of `rumba run`; the command is ``daemon.cli.commands.run``."""

from __future__ import annotations

import argparse
from pathlib import Path


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.run import cmd_run

    return cmd_run(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the verification service (sessions, triggers, HMI)")
    p.add_argument("--config", required=True, help="daemon.yaml")
    p.add_argument("--check", action="store_true",
                   help="validate the configuration (and files it names) and exit")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--log-file", type=Path, metavar="FILE",
                   help="log to FILE, rotated at --log-max-mb with 5 older files kept "
                        "(default: stderr, i.e. the journal under systemd)")
    p.add_argument("--log-max-mb", type=int, default=10, metavar="N",
                   help="size at which --log-file rotates (default 10 MiB)")
    p.set_defaults(func=_run)
