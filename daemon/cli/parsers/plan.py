"""The arguments of `rumba plan`; the command is ``daemon.cli.commands.plan``."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from daemon.cli.choices import DIALECT_NAMES


def ascii_seconds(text: str) -> float:
    """Seconds as plain ASCII decimals: Python's float() also reads '１' (fullwidth),
    '1_0' or 'nan', which no operator means to type."""
    if not re.fullmatch(r"[0-9]{1,7}(\.[0-9]*)?|\.[0-9]+", text):
        raise argparse.ArgumentTypeError(f"{text!r}: expected seconds as a plain decimal "
                                         "number such as 90 or 90.5")
    return float(text)


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.plan import run

    return run(args)


def _check(args: argparse.Namespace) -> None:
    from daemon.cli import arguments

    arguments.inputs(args, ("machine", "artefact", "target"))
    arguments.output_folder(args.output, str(args.output))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan", help="optimise the poses of a plan: target link uncertainties, least time",
        description="Choose the B/C poses (a grid of the reachable indexations that pass the "
                    "safety check) and their order so that every link of the target file "
                    "reaches its standard uncertainty in the least estimated machine time; "
                    "write the plan and print its predicted uncertainties and time beside "
                    "the reference plan's. Exit 0; 1 when --max-time leaves targets missed "
                    "(the plan is written and they are named); 2 on bad input.")
    p.add_argument("--machine", type=Path, required=True, metavar="M.yaml")
    p.add_argument("--artefact", type=Path, required=True, metavar="A.yaml")
    p.add_argument("--target", type=Path, required=True, metavar="TARGETS.yaml",
                   help="target file (example: config/plans/targets/shift_start.yaml)")
    p.add_argument("--max-time", type=ascii_seconds, metavar="S",
                   help="cap on the estimated machine time (seconds)")
    p.add_argument("--dialect", default="fanuc", choices=[*sorted(DIALECT_NAMES)],
                   help="the controller's dialect: it decides the two-speed touch and so the "
                        "time (default: fanuc)")
    p.add_argument("-o", "--output", type=Path, metavar="PLAN.yaml",
                   help="plan file to write (default: <name>.yaml here)")
    p.add_argument("--force", action="store_true", help="overwrite the output file")
    p.set_defaults(func=_run, preflight=_check)
