"""The arguments of `rumba gcode`; the command is ``daemon.cli.commands.gcode``."""

from __future__ import annotations

import argparse
from pathlib import Path

from daemon.cli.choices import GCODE_DIALECTS


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.gcode import run

    return run(args)


def _check(args: argparse.Namespace) -> None:
    from daemon.cli import arguments

    arguments.inputs(args, ("machine", "artefact", "plan", "targets"))
    arguments.output_folder(args.output, str(args.output))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "gcode", help="generate a checked probing program for one controller dialect",
        description="Generate the probing program of a plan (every pose: index, then five "
                    "touches per ball), refuse it when it leaves the travel or enters a keep-out "
                    "volume, and print the touch count, the estimated cycle time and its lower "
                    "bound.")
    p.add_argument("--machine", type=Path, required=True, metavar="M.yaml")
    p.add_argument("--artefact", type=Path, required=True, metavar="A.yaml")
    p.add_argument("--plan", type=Path, required=True, metavar="P.yaml")
    p.add_argument("--dialect", required=True, choices=[*GCODE_DIALECTS, "haas"])
    p.add_argument("-o", "--output", type=Path, metavar="FILE",
                   help="write the program here (auxiliary files next to it); default: stdout")
    p.add_argument("--targets", type=Path, metavar="estimate.json",
                   help="ball/stylus setup errors of the last run (`rumba analyze --json`): "
                        "targets from the estimate, smaller standoff and overtravel")
    p.set_defaults(func=_run, preflight=_check)
