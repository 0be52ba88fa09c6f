"""The arguments of `rumba baseline`; the command is ``daemon.cli.commands.baseline``."""

from __future__ import annotations

import argparse

DESCRIPTION = ("``rumba baseline show MACHINE`` prints the run a machine's drift is judged "
               "against (who set it and when) and any proposal waiting; ``rumba baseline set "
               "MACHINE RUN --by NAME`` makes a finished run the baseline (or confirms the "
               "proposed one), journaled with the name and the time; a run that FAILed, "
               "predates a compensation or is older than the controller's model is refused "
               "unless ``--override REASON`` (journaled).")


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.baseline import cmd_baseline

    return cmd_baseline(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("baseline", help="show or set the run a machine's drift is judged "
                       "against (a person confirms it)", description=DESCRIPTION)
    p.add_argument("action", choices=("show", "set"))
    p.add_argument("machine", help="machine name in daemon.yaml")
    p.add_argument("run", nargs="?", help="with set: the run id (default: the proposed one)")
    p.add_argument("--config", required=True, help="daemon.yaml")
    p.add_argument("--by", help="with set: who sets it (a person's name, journaled)")
    p.add_argument("--note", default="", help="with set: why (journaled)")
    p.add_argument("--override", metavar="REASON",
                   help="with set: make a run the baseline although it FAILed, predates a "
                        "compensation or was identified against a model the controller no "
                        "longer runs; the reason is journaled with the objections")
    p.set_defaults(func=_run)
