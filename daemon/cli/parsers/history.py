"""The arguments of `rumba history`; the command is ``daemon.cli.commands.history``."""

from __future__ import annotations

import argparse


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.history import cmd_history  # looked up on each run (tests patch it)

    return cmd_history(args)


def _check(args: argparse.Namespace) -> None:
    from daemon.cli import arguments

    arguments.inputs(args, ("config", "import_csv"))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("history", help="list runs and trends; export/import probing logs")
    p.add_argument("--config", required=True, help="daemon.yaml (names the journal)")
    p.add_argument("--machine", help="only this machine (required with --import)")
    p.add_argument("--limit", type=int, default=20, help="runs to list (default 20)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--export", metavar="RUN",
                   help="export run RUN to --csv, or map result RUN to --json (its map file)")
    g.add_argument("--import", dest="import_csv", metavar="CSV", help="import a probing log")
    g.add_argument("--export-aqdef", metavar="FILE",
                   help="write the machine's completed runs and map results as an AQDEF "
                        "(Q-DAS .dfq) SPC file")
    g.add_argument("--against-temperature", metavar="CHANNEL",
                   help="a link error (--link) against this temperature channel over the "
                        "machine's runs: r and slope ± u")
    p.add_argument("--link", help="--against-temperature: the link error, e.g. EX0C")
    p.add_argument("--plot", metavar="PNG", help="--against-temperature: also a scatter plot")
    p.add_argument("--csv", metavar="OUT", help="output file for --export of a run")
    p.add_argument("--json", metavar="OUT", help="output file for --export of a map result")
    p.add_argument("--no-analyse", action="store_true", help="--import: journal only")
    p.set_defaults(func=_run, preflight=_check)
