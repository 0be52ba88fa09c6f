"""The arguments of `rumba sim` (with ``simulators.serve``'s); the command: ``commands.sim``."""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from daemon.cli.choices import DIALECT_NAMES
from daemon.cli.parsers import add_later


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.sim import main

    return main(args)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sim", help="software CNC with injected errors: run a program offline or serve it",
        description="Simulated five-axis machine: true chain + link/setup errors + effects + "
                    "probe physics, executing our G-code dialects.")
    p.add_argument("--machine", required=True, type=Path, help="machine YAML")
    p.add_argument("--artefact", required=True, type=Path, help="artefact YAML")
    p.add_argument("--errors", type=Path, help="errors YAML (default: a perfect machine)")
    p.add_argument("--seed", type=int, help="random seed (default: the errors file's seed)")
    p.add_argument("--time-scale", type=float, default=0.0,
                   help="0 = as fast as possible (default), 1 = real time")
    p.add_argument("--faults", type=Path, help="faults YAML (simulators/faults.py)")
    p.add_argument("--run", type=Path, metavar="PROGRAM", help="execute this program offline")
    p.add_argument("--dialect", choices=DIALECT_NAMES,
                   help="dialect of --run PROGRAM; with --serve, the control's own (its DNC "
                        "tapes and the console's `run FILE`)")
    p.add_argument("--log", type=Path, metavar="OUT.csv", help="probing log to write (--run)")
    p.add_argument("--run-id", help="run_id column of the log (default: program file stem)")
    if importlib.util.find_spec("simulators.serve") is not None:  # --serve and its options
        add_later(p, _serve_arguments)
    p.set_defaults(func=_run)


def _serve_arguments(p: argparse.ArgumentParser) -> None:
    import simulators.serve as serve  # asyncio: imported when `rumba sim` runs, not for --help

    serve.add_arguments(p)
