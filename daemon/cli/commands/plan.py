"""``rumba plan``: choose the B/C poses and their order that reach target link uncertainties in
the least machine time, write them as a plan, and compare with the reference plan."""

from __future__ import annotations

import argparse
import errno
import os
import sys
import time
from pathlib import Path

from contracts.setup_files import Plan
from identification.harmonic_support import warnings as harmonic_warnings
from identification.kinematics import Machine
from programs.dialects import get_dialect
from programs.plan_make import Outcome, PlanMakeError, make_plan


def write_new(out: Path, text: str, force: bool) -> None:
    """Write the plan file itself, never through a symbolic link (a planted link would send a
    root-run `rumba plan` anywhere): O_NOFOLLOW, and O_EXCL unless ``force``."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | (os.O_TRUNC if force else os.O_EXCL)
    try:
        fd = os.open(out, flags, 0o644)
    except OSError as e:
        if out.is_symlink():
            raise _error(f"{out}: is a symbolic link; refusing to write through it") from None
        if e.errno == errno.EEXIST:
            raise _error(f"{out}: exists; choose another --output or add --force") from None
        raise _error(f"{out}: cannot write: {e.strerror}") from None
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)


def run(args: argparse.Namespace) -> int:
    from contracts.plan_targets import load_targets_file
    from daemon.safepath import plain_name

    out = args.output or Path(plain_name(f"{load_targets_file(args.target).name}.yaml",
                                         "name"))
    if out.is_symlink():  # checked again when written (write_new): this saves the work
        raise _error(f"{out}: is a symbolic link; refusing to write through it")
    if out.exists() and not args.force:
        raise _error(f"{out}: exists; choose another --output or add --force")
    try:
        r = make_plan(args.machine, args.artefact, args.target, args.dialect, args.max_time)
    except PlanMakeError as e:
        raise _error(str(e)) from None
    _print(r, get_dialect(args.dialect), r.chosen.design.sigma_um if r.chosen.design else ())
    write_new(out, r.text, args.force)
    print(f"wrote {out}")
    if r.chosen.missed:
        print(f"rumba plan: --max-time {args.max_time:g} s: targets missed: " + "; ".join(
            f"{k} u {u:.3g} > {t:.3g} {_unit(k)}" for k, (u, t) in r.chosen.missed.items()),
            file=sys.stderr)
        return 1
    return 0


def _error(msg: str) -> Exception:
    from daemon.cli.main import UserError  # late import: only on an error
    return UserError(msg)


def _unit(link: str) -> str:
    return "µrad" if link[1] in "ABC" else "µm"


def _now() -> str:
    return time.strftime("%Y-%m-%d %H:%M")


def _mmss(s: float) -> str:
    m, sec = divmod(round(s), 60)
    return f"{m} min {sec:02d} s"


def _print(r: Outcome, dialect: object, sigma: object) -> None:
    plan, ref, old, new = r.plan, r.reference, r.old, r.new
    two = getattr(dialect, "two_speed", False) and plan.feeds.fast_probe_mm_min
    print(f"{new.program.machine.name} x {new.program.artefact.name}, dialect "
          f"{getattr(dialect, 'label', '')} ({'two-speed' if two else 'one-speed'} touch); "
          f"predicted with centre repeatability {'/'.join(f'{s:g}' for s in sigma)} µm "
          f"(x/y/z); {r.assumed_index}")
    w = max(len(ref.name), len(plan.name), 12)
    print(f"{'':22}{ref.name:>{w}}  {plan.name:>{w}}  {'target':>8}")
    visits = (len(ref.poses) * ref.repeats + ref.drift_check, len(plan.poses) + 1)
    print(f"{'poses (visits)':22}{len(ref.poses):>{w - 5}} ({visits[0]:>2})  "
          f"{len(plan.poses):>{w - 5}} ({visits[1]:>2})")
    print(f"{'touches':22}{len(old.touches):>{w}}  {len(new.touches):>{w}}")
    pct = f"{100 * new.estimated_s / old.estimated_s:.0f} %"
    print(f"{'machine time':22}{_mmss(old.estimated_s):>{w}}  {_mmss(new.estimated_s):>{w}}"
          f"  {pct:>8}")
    print(f"{'  lower bound':22}{_mmss(old.lower_bound_s):>{w}}  "
          f"{_mmss(new.lower_bound_s):>{w}}")
    for k in r.new_u:
        t = f"{r.targets[k]:#.3g}" if k in r.targets else "-"
        u_ref = f"{r.ref_u[k]:#.3g}" if k in r.ref_u else "-"
        ok = "" if k not in r.targets else ("  met" if r.new_u[k] <= r.targets[k] * (1 + 1e-9)
                                            else "  MISSED")
        print(f"{'u ' + k + ' ' + _unit(k):22}{u_ref:>{w}}  {r.new_u[k]:>#{w}.3g}  {t:>8}{ok}")
    if r.drift_u:
        worst = max(r.drift_u, key=lambda k: r.drift_u[k] / r.new_u[k])  # type: ignore[index]
        print(f"drift: the first pose is probed again at the end and the time order is not "
              f"monotone in C; with a drift estimated too (linear, or a warm-up of τ 10-60 min"
              f" and τ estimated), u grows at most ×"
              f"{r.drift_u[worst] / r.new_u[worst]:.2f} ({worst})")
    if r.drift is not None:
        for name, d in zip((ref.name, plan.name), r.drift, strict=True):
            for line in d.lines(name):
                print(line)
    _harmonic_warnings(plan, new.program.machine)
    c = r.chosen
    print(f"optimiser {r.optimiser_s:.1f} s: {c.builds} one-pose programs built and checked, "
          f"{len(c.excluded)} candidate poses refused by the safety check"
          + ("; stopped at its time budget" if c.stopped else ""))
    for why in c.refused:
        print(f"excluded after the whole program refused it: {why}")


def _harmonic_warnings(plan: Plan, machine: Machine) -> None:
    """A plan with validate poses: which rotary positioning harmonics its estimate poses cannot
    identify for `rumba gap --holdout` (``identification.harmonic_support``)."""
    val = [p for p in plan.poses if p.role == "validate"]
    if not val:
        return
    est = [p for p in plan.poses if p.role != "validate"]
    first, second = machine.rotary_axes

    def axes(poses: list) -> dict[str, list[float]]:
        return {first: [p.b_deg for p in poses], second: [p.c_deg for p in poses]}

    for m in harmonic_warnings(axes(est), axes(val)):
        print(f"warning (rumba gap --holdout): {m}")
