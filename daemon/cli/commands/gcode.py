"""``rumba gcode``: generate a probing program, check it, print touch count and cycle time."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from contracts.setup_files import check_touch_count, load_artefact, load_machine, load_plan
from daemon.cli.main import UserError
from daemon.safepath import contained_path
from programs.dialects import DIALECTS


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
    p.add_argument("--dialect", required=True, choices=[*sorted(DIALECTS), "haas"])
    p.add_argument("-o", "--output", type=Path, metavar="FILE",
                   help="write the program here (auxiliary files next to it); default: stdout")
    p.add_argument("--targets", type=Path, metavar="estimate.json",
                   help="ball/stylus setup errors of the last run (`rumba analyze --json`): "
                        "targets from the estimate, smaller standoff and overtravel")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from programs.generate import generate
    from programs.geometry import ProgramError
    from programs.model import load_targets
    from programs.safety import SafetyError

    machine, mfile = load_machine(args.machine)
    artefact = load_artefact(args.artefact)
    plan = load_plan(args.plan)
    check_touch_count(plan, artefact, f"{args.plan}: poses")  # before anything is allocated
    targets = load_targets(args.targets, artefact) if args.targets else None
    t0 = time.perf_counter()
    try:
        g = generate(machine, mfile, artefact, plan, args.dialect, targets)
    except SafetyError as e:
        raise UserError(f"unsafe program refused: {e}") from None
    except ProgramError as e:
        raise UserError(f"cannot generate the program: {e}") from None
    gen_s = time.perf_counter() - t0
    if args.output:
        try:
            args.output.write_text(g.text, encoding="ascii")
            for name, body in g.aux_files.items():
                contained_path(args.output.parent, name).write_text(body, encoding="ascii")
        except OSError as e:
            raise UserError(f"{args.output}: cannot write: {e.strerror}") from None
    else:
        sys.stdout.write(g.text)
    out = sys.stderr if not args.output else sys.stdout
    report = g.safety
    print(f"{g.dialect.name}: {len(g.touches)} touches, {len(plan.poses)} poses × "
          f"{len(artefact.balls)} balls × {plan.repeats} repeat(s)"
          f"{' + first pose again (drift check)' if plan.drift_check else ''}, targets "
          f"{g.program.targets.source}"
          f"; {g.cycle_time.summary()}; safety: {report.moves} blocks checked, the closest "
          f"non-probing move passes {report.min_slack_mm:.3f} mm beyond the required "
          f"standoff/clearance of a ball, rod or keep-out it does not probe; generated in "
          f"{gen_s:.2f} s", file=out)
    return 0
