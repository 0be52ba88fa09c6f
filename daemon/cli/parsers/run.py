"""The arguments of `rumba run`; the command is ``daemon.cli.commands.run``."""

from __future__ import annotations

import argparse


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.run import cmd_run

    return cmd_run(args)


def _check(args: argparse.Namespace) -> None:
    from daemon.cli import arguments

    arguments.inputs(args, ("config",))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the verification service (sessions, triggers, HMI)")
    p.add_argument("--config", required=True, help="daemon.yaml")
    p.add_argument("--check", action="store_true",
                   help="validate the configuration (and files it names) and exit")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.set_defaults(func=_run, preflight=_check)
