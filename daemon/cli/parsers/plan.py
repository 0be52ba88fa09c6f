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
    if args.map:
        from daemon.cli.commands.plan_map import run_map_plan

        return run_map_plan(args)
    from daemon.cli.commands.plan import run

    args.artefact = args.artefact[0]
    return run(args)


def _check(args: argparse.Namespace) -> None:
    from daemon.cli import arguments

    if args.map:
        if args.budget_min is None:
            raise arguments.user_error("--map: give the machine-time budget --budget-min MIN")
        if args.target is not None or args.max_time is not None:
            raise arguments.user_error("--map plans a map of the linear axes: --target and "
                                       "--max-time are for link targets (give --budget-min)")
    else:
        for k in ("budget_min", "box", "min_coverage", "tilt_max_deg", "plan"):
            if getattr(args, k) is not None:
                raise arguments.user_error(f"--{k.replace('_', '-')}: only with --map")
        if args.target is None:
            raise arguments.user_error("give --target TARGETS.yaml (or --map for a map plan)")
        if len(args.artefact) != 1:
            raise arguments.user_error("one --artefact (several are the placements of --map)")
    args.min_coverage = 0.5 if args.min_coverage is None else args.min_coverage
    args.tilt_max_deg = 60.0 if args.tilt_max_deg is None else args.tilt_max_deg
    arguments.inputs(args, ("machine", "artefact", "target", "plan"))
    arguments.output_folder(args.output, str(args.output))


def _minutes(text: str) -> float:
    if not re.fullmatch(r"[0-9]{1,5}(\.[0-9]*)?|\.[0-9]+", text):
        raise argparse.ArgumentTypeError(f"{text!r}: expected minutes as a plain decimal "
                                         "number such as 20 or 12.5")
    return float(text)


def _degrees(text: str) -> float:
    if not re.fullmatch(r"[0-9]{1,3}(\.[0-9]*)?", text):
        raise argparse.ArgumentTypeError(f"{text!r}: expected degrees such as 60")
    return float(text)


def _fraction(text: str) -> float:
    if not re.fullmatch(r"(0?\.[0-9]+|1(\.0*)?)", text) or float(text) == 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a fraction in (0, 1] such as 0.5")
    return float(text)


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
    p.add_argument("--artefact", type=Path, required=True, metavar="A.yaml", action="append",
                   help="the artefact file; with --map, repeated: the placements, in the "
                        "order the operator sets them")
    p.add_argument("--target", type=Path, metavar="TARGETS.yaml",
                   help="target file (example: config/plans/targets/shift_start.yaml)")
    p.add_argument("--max-time", type=ascii_seconds, metavar="S",
                   help="cap on the estimated machine time (seconds)")
    p.add_argument("--dialect", default="fanuc", choices=[*sorted(DIALECT_NAMES)],
                   help="the controller's dialect: it decides the two-speed touch and so the "
                        "time (default: fanuc)")
    p.add_argument("-o", "--output", type=Path, metavar="PLAN.yaml",
                   help="plan file to write (default: <name>.yaml here)")
    p.add_argument("--force", action="store_true", help="overwrite the output file")
    m = p.add_argument_group("map of the linear axes (--map)")
    m.add_argument("--map", action="store_true",
                   help="plan a map of the linear axes (rumba map): placements and poses "
                        "covering a volume within --budget-min; writes the map-job file "
                        "(-o, default map-job.yaml) and one plan file per placement beside it")
    m.add_argument("--budget-min", type=_minutes, metavar="MIN",
                   help="machine-time budget of the whole map (minutes, estimated)")
    m.add_argument("--box", metavar="X0,X1,Y0,Y1,Z0,Z1",
                   help="the volume to cover (mm, controller coordinates); default: the "
                        "machine's strokes")
    m.add_argument("--min-coverage", type=_fraction, metavar="F",
                   help="refuse unless the plan covers this fraction of the volume on every "
                        "axis (default 0.5)")
    m.add_argument("--tilt-max-deg", type=_degrees, metavar="DEG",
                   help="largest tilt of the first rotary axis tried (default 60)")
    m.add_argument("--plan", type=Path, metavar="BASE.yaml",
                   help="take the stylus, feeds and clearances of this plan (its poses are "
                        "ignored); default those of config/plans/thesis_map_36poses.yaml")
    p.set_defaults(func=_run, preflight=_check)
