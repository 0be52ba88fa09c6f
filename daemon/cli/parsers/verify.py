"""The arguments of `rumba verify`; the command is ``daemon.cli.commands.verify``."""

from __future__ import annotations

import argparse


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.verify import cmd_verify

    return cmd_verify(args)


def _check(args: argparse.Namespace) -> None:
    from daemon.cli import arguments

    arguments.inputs(args, ("config",))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("verify", help="run one verification now (exit 0 pass, 1 fail, 2 error)")
    p.add_argument("--config", required=True, help="daemon.yaml")
    p.add_argument("--machine", required=True, help="machine name in daemon.yaml")
    p.add_argument("--strict", action="store_true", help="exit 1 on WARN too")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--operator", metavar="NAME",
                   help="the person starting the run (on the report's 'Started by' and "
                        "'Prepared by'; with --daemon journaled by the daemon as well)")
    p.add_argument("--daemon", action="store_true",
                   help="ask the running daemon of this config (through its HMI API) instead "
                        "of driving the link from this process")
    p.add_argument("--map", action="store_true",
                   help="run the machine's map job (daemon.yaml map_job: its placements, the "
                        "operator prompted between them; Enter continues, as the HMI's "
                        "Continue) and fit the map; exit 0 done, 1 when the map's volumetric "
                        "error FAILs its limit, 2 otherwise")
    p.set_defaults(func=_run, preflight=_check)
