"""The arguments of `rumba compensate`; the command is ``daemon.cli.commands.compensate``."""

from __future__ import annotations

import argparse

DESCRIPTION = ("``rumba compensate RUN --config daemon.yaml``: the controller-model changes that "
               "hold the run's identified link errors, guarded and worth writing, listed "
               "address by address as the program would write them; a review document "
               "(proposal-<machine>-<run>.json), never a program. ``--confirm --by NAME`` "
               "writes the program and applies it, ``--rollback`` restores the values before "
               "the last applied compensation. Exit 0 done, 2 refused.")


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.compensate import cmd_compensate

    return cmd_compensate(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compensate", help="write the identified link errors back into the "
                       "controller's kinematic model (guarded, journaled, reversible)",
                       description=DESCRIPTION)
    p.add_argument("run", nargs="?", help="run id (a verification run in the journal)")
    p.add_argument("--config", required=True, help="daemon.yaml")
    p.add_argument("--machine", help="machine name in daemon.yaml (default: the run's)")
    p.add_argument("--confirm", action="store_true",
                   help="apply the proposal (operator confirmation; needs --by)")
    p.add_argument("--rollback", action="store_true",
                   help="restore the values before the last applied compensation (needs "
                        "--machine and --by)")
    p.add_argument("--by", help="who confirms (recorded in the journal); 'unattended' only "
                                "where the machine's guards allow it")
    p.add_argument("--again", action="store_true",
                   help="with --confirm: apply a run whose compensation was rolled back, as a "
                        "new decision (refused without it)")
    p.add_argument("--listing", metavar="FINGERPRINT",
                   help="with --confirm: the listing fingerprint of the proposal reviewed (its "
                        "review document and output print it); refused if what would be "
                        "written now differs")
    p.add_argument("--verify", action="store_true",
                   help="with --confirm: when the values went live (LinuxCNC on this PC), run "
                        "the verification at once and print each link before and after")
    p.set_defaults(func=_run)
