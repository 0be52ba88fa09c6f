"""``rumba gcode``: generate a probing program, check it, print touch count and cycle time."""

from __future__ import annotations

import argparse
import sys
import time

from contracts.setup_files import check_touch_count, load_artefact, load_machine, load_plan
from daemon.cli.main import UserError
from daemon.safepath import contained_path


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
    written = []
    if args.output:
        try:
            args.output.write_text(g.text, encoding="ascii")
            written.append(args.output)
            for name, body in g.aux_files.items():
                aux = contained_path(args.output.parent, name)
                aux.write_text(body, encoding="ascii")
                written.append(aux)
        except OSError as e:
            raise UserError(f"{args.output}: cannot write: {e.strerror}") from None
    else:
        sys.stdout.write(g.text)
    out = sys.stderr if not args.output else sys.stdout
    report = g.safety
    print(f"{g.dialect.label}: {len(g.touches)} touches, {len(plan.poses)} poses × "
          f"{len(artefact.balls)} balls × {plan.repeats} repeat(s)"
          f"{' + first pose again (drift check)' if plan.drift_check else ''}, targets "
          f"{g.program.targets.source}"
          f"; {g.cycle_time.summary()}; safety: {report.moves} blocks checked, the closest "
          f"non-probing move passes {report.min_slack_mm:.3f} mm beyond the required "
          f"standoff/clearance of a ball, rod or keep-out it does not probe; generated in "
          f"{gen_s:.2f} s", file=out)
    for path in written:  # every file the command wrote, by the path it was given
        print(f"wrote {path}", file=out)
    return 0
