"""`rumba gap`: where a probing log departs from the twin, which effect explains it, how much."""

from __future__ import annotations

import argparse
import json
import warnings
from collections.abc import Sequence
from importlib import resources
from pathlib import Path

import numpy as np

from contracts.probing_log import LogRow, ProbeLogError, read_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis import centres_input
from daemon.analysis.touch_centres import columns, one_run_balls
from daemon.cli.arguments import parse_families, parse_repeatability
from daemon.cli.choices import DEFAULT_STYLUS_DIAMETER_MM
from identification.effects import FAMILIES, Effect, library
from identification.gap import Options, TouchData, diagnose
from identification.gap.chip_floor import message as chip_message
from identification.gap.locate import shown_locations
from identification.gap.outlier_visits import name as outlier_name
from identification.harmonic_support import warnings as harmonic_warnings
from identification.kinematics import Machine
from identification.model import Artefact

# the thesis machine, artefact and annex B plan of the self-check, shipped with the package
# (copies of config/machines, config/artefacts, config/plans; tests/test_cli_defaults.py)
DEFAULTS = ("thesis_wcbxfzyt.yaml", "thesis_4ball.yaml", "thesis_annexB_14poses.yaml")


def default_file(name: str) -> Path:
    """A default setup file of the self-check, found in the installed package (not a checkout's
    config/ folder): ``daemon/cli/defaults/<name>``."""
    if name not in DEFAULTS:
        raise ValueError(f"{name}: not a shipped default ({', '.join(DEFAULTS)})")
    return Path(str(resources.files("daemon.cli").joinpath("defaults", name)))


def _user_error(msg: str) -> Exception:
    from daemon.cli.main import UserError  # late import: only on an error

    return UserError(msg)


def touches_from_rows(rows: Sequence[LogRow], artefact: Artefact, source: str) -> TouchData:
    """Probing-log rows → touch arrays (one run only: setups differ between runs)."""
    col = columns(rows, ("run_id", "repeat", "pose", "ball", "touch", "t_s", "b_deg", "c_deg",
                         "dir_x", "dir_y", "dir_z", "x_mm", "y_mm", "z_mm"))
    _, ball = one_run_balls(col, artefact, source, "diagnose")
    d = np.stack([col["dir_x"], col["dir_y"], col["dir_z"]], axis=1).reshape(-1, 3)
    n = np.linalg.norm(d, axis=1)
    if np.any(n < 1e-9):
        raise ProbeLogError(f"{source}: a touch has a zero approach direction (dir_x/y/z)")
    return TouchData(
        repeat=col["repeat"], pose=col["pose"],
        ball=ball, touch=col["touch"],
        t_s=col["t_s"], b_deg=col["b_deg"], c_deg=col["c_deg"], direction=d / n[:, None],
        xyz_mm=np.stack([col["x_mm"], col["y_mm"], col["z_mm"]], axis=1).reshape(-1, 3))


def _families(text: str | None) -> tuple[str, ...]:
    return parse_families(text, FAMILIES)


def _known(values: Sequence[str] | None, machine: Machine, artefact: Artefact,
           gravity: Sequence[float] | None) -> list[Effect]:
    """``--known`` values (repeatable, each a comma list of FAMILY or FAMILY:AXIS; a family
    alone = every instance of it) → library effects, to be fitted with the twin."""
    lib = library(machine, artefact.ids, gravity_dir=gravity)
    out: list[Effect] = []
    for text in values or []:
        for item in (x.strip() for x in text.split(",")):
            if not item:
                continue
            family, _, axis = item.partition(":")
            hits = [e for e in lib if e.family == family.strip()
                    and (not axis or (e.axis or "").lower() == axis.strip().lower())]
            if not hits or (axis and hits[0].axis is None):
                choices = ", ".join(
                    f + (f"[:{'|'.join(a for a in axes if a)}]" if any(axes) else "")
                    for f in FAMILIES
                    if (axes := [e.axis for e in lib if e.family == f]))
                raise _user_error(f"--known: unknown effect {item!r}; expected FAMILY or "
                                  f"FAMILY:AXIS among {choices}")
            out += [e for e in hits if e not in out]
    return out


def _fmt_params(params: dict) -> str:
    return ", ".join(f"{k} = {p['value']:.3g}" + (f" ± {p['std']:.2g}" if p["std"] is not None
                                                   else "") + f" {p['unit']}"
                     for k, p in params.items())


def _print_report(rep: dict) -> None:
    b, v = rep["baseline"], rep["verdict"]
    touch = (f"touch repeatability {rep['noise']['sigma_touch_um']:.3f} µm"
             if rep["noise"]["source"].startswith("sphere-fit") else rep["noise"]["source"])
    print(f"noise floor {rep['noise_floor_um']:.3f} µm (per coordinate; {touch}); "
          f"split: {rep['split']}")
    print(f"twin gap: train RMS {b['train_rms_um']:.3f} µm, held-out RMS "
          f"{b['holdout_rms_um']:.3f} µm, max {b['holdout_max_um']:.3f} µm "
          f"({b['gap_ratio']:.2f}× the held-out floor, p = {b['p_value']:.2g})")
    parts = rep["noise"].get("parts")
    if parts:
        print(parts["message"])
    if rep.get("scatter"):
        print(f"per-visit scatter: {rep['scatter']['message']}")
    st = rep.get("structure")
    if st:
        print(f"{'STRUCTURE' if st['found'] else 'structure'}: {st['message']}"
              + ("; the selected effects remove it" if st.get("explained_by_selected") else ""))
    if rep.get("ball_step"):
        print(f"ball moved: {rep['ball_step']['message']}")
    if rep.get("links"):
        print("links (±u, with the scatter and the selected effects): " + ", ".join(
            f"{n} {x['value']:+.1f} ± {x['std']:.1f} {'µrad' if x['unit'] == 'urad' else 'µm'}"
            for n, x in rep["links"].items()))
    for k in rep["known"]:
        how = "fitted with the twin" if k["fitted"] else "given"
        label = k["effect"] + (f":{k['axis']}" if k["axis"] else "")
        print(f"known ({how}): {label}: {_fmt_params(k['params']) or 'not visible'}")
    tc = rep.get("time_check")
    if tc:
        print(f"drift checked on {tc['split']}: explains {100 * tc['explained_fraction']:.0f} % "
              f"of the held-out excess (leaving poses out {100 * tc['explained_fraction_pose']:.0f}"
              f" %) — {'confirmed' if tc['confirmed'] else 'NOT confirmed'}")
    chip = chip_message(rep.get("outlier_test", {}).get("min_chip_um") or
                        {"pole": None, "equator": None})
    if chip:
        print(f"note: {chip}")
    for o in rep.get("outliers", ()):
        print(f"measurement outlier: {outlier_name(o)}, robust z {o['score']:.0f} ({o['stage']}"
              " stage): left out of the diagnosis")
    for o in rep.get("explained_visits", ()):  # a pattern across visits
        print(f"not a chip: {outlier_name(o)} departs as {o['explained_by']} predicts for every "
              "visit: kept in the diagnosis")
    shown, more, below = shown_locations(rep["location"], rep["breakdowns"])
    for loc in shown:
        print(f"  gap at {loc['by']} {loc['key']}: {loc['rms_um']:.3f} µm "
              f"({loc['ratio_to_floor']:.1f}× floor)"
              + ("" if loc["significant"] else ", not significant alone"))
    rest = [f"{more} more above the floor"] * bool(more) + [f"{below} below it"] * bool(below)
    if rest:
        print(f"  … {' and '.join(rest)} (every cell: --json, --html)")
    print(f"{'candidate':34s} {'held-out µm':>11s} {'explained':>9s}  sig  p-value")
    for c in rep["candidates"][:8]:
        label = c["effect"] + (f":{c['axis']}" if c["axis"] else "")
        alike = f"  ~ {', '.join(c['indistinguishable_from'])}" if c["indistinguishable_from"] \
            else ""
        print(f"{label:34s} {c['holdout_rms_um']:11.3f} {100 * c['explained_fraction']:8.0f}%"
              f"  {'yes' if c['significant'] else 'no ':3s}  {c['p_value']:.2g}{alike}")
    for a in rep["absorbed"]:
        print(f"absorbed: {a['effect']} {a['value_um']:+.2f} ± {a['std_um']:.2f} µm — {a['what']}")
    if rep["dropped_groups"]:
        print(f"note: {rep['dropped_groups']} incomplete ball-pose(s) left out")
    for inv in rep["invisible"]:
        print(f"invisible: {inv['effect']}:{inv['axis']} — {inv['reason']}")
    axis = f":{v['axis']}" if v["axis"] else ""
    print(f"verdict: {v['effect']}{axis} — held-out RMS {v['holdout_rms_before_um']:.3f} → "
          f"{v['holdout_rms_after_um']:.3f} µm; {v['message']}")


def _load(path: str, artefact: Artefact) -> TouchData:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rows = read_log(path, artefact)
    for w in caught:
        print(f"warning: {w.message}")
    return touches_from_rows(rows, artefact, path)


def _indexations(data: TouchData) -> np.ndarray:
    """One (b, c) per visit (repeat, pose) of a log."""
    _, first = np.unique(np.c_[data.repeat, data.pose], axis=0, return_index=True)
    return np.c_[data.b_deg[first], data.c_deg[first]]


def _plan_warnings(machine: Machine, train_bc: np.ndarray, hold_bc: np.ndarray | None) -> None:
    """Say which rotary positioning harmonics the estimate poses cannot identify: a
    candidate fitted there and judged on the hold-out would otherwise just under-perform."""
    first, second = machine.rotary_axes

    def axes(bc: np.ndarray) -> dict[str, np.ndarray]:
        return {first: bc[:, 0], second: bc[:, 1]}

    for m in harmonic_warnings(axes(train_bc), None if hold_bc is None else axes(hold_bc)):
        print(f"warning: {m} — shipped plan with a hold-out that identifies orders 1-2: "
              "config/plans/shift_holdout_14poses.yaml")


def _selfcheck(args: argparse.Namespace) -> int:
    from identification.gap import selfcheck

    machine, mfile = load_machine(args.machine or default_file("thesis_wcbxfzyt.yaml"))
    artefact = load_artefact(args.artefact or default_file("thesis_4ball.yaml"))
    plan = load_plan(default_file("thesis_annexB_14poses.yaml"))
    plans = {"thesis-14": [(p.b_deg, p.c_deg) for p in plan.poses]}
    if args.full:
        plans["grid-49"] = selfcheck.grid_49()
    seeds = args.seeds or (10 if args.full else 2)
    stylus_r = (args.stylus_diameter_mm or plan.stylus_diameter_mm) / 2

    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    total = len(plans) * len(selfcheck.SCENARIOS) * seeds
    done = 0

    def show(c: selfcheck.Case) -> None:
        nonlocal done
        done += 1
        scenario = f"{c.scenario}:{c.axis}" if c.axis else c.scenario
        top = f"{c.top}:{c.top_axis}" if c.top_axis else str(c.top)
        print(f"{done:{len(str(total))}d}/{total} {c.plan:10s} {scenario:28s} → "
              f"{c.verdict:22s} top {top:28s} after/floor {c.after_ratio:4.2f} "
              f"{'ok' if c.ok else 'MISS'}", flush=True)
        bar.update(task, completed=done)

    # the bar on stderr (the terminal), the case lines and the table on stdout (a log)
    with Progress(TextColumn("self-check"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("cases,"), TimeElapsedColumn(), TextColumn("elapsed,"),
                  TimeRemainingColumn(), TextColumn("left"),
                  console=Console(stderr=True)) as bar:
        task = bar.add_task("self-check", total=total)
        summary = selfcheck.run(machine, artefact, plans, stylus_r, seeds, progress=show,
                                split=args.split, gravity_dir=mfile.gravity)
    print()
    print(summary.table())
    rates = summary.rates()
    need = {k: (0.95 if k.startswith("null") else 0.9) for k in rates}
    failed = [k for k, r in rates.items() if r < need[k]]
    print("targets met" if not failed else f"targets missed: {', '.join(failed)}")
    return 0 if not failed else 1


def _write(path: str, text: str, flag: str) -> None:
    try:
        Path(path).write_text(text, encoding="utf-8")
    except OSError as e:
        raise _user_error(f"{flag} {path}: cannot write: {e.strerror}") from None


def cmd_gap(args: argparse.Namespace) -> int:
    """`rumba gap` (``daemon.cli.parsers.gap``): the self-check or one diagnosis."""
    if args.selfcheck:
        return _selfcheck(args)
    if not ((args.log or args.centres) and args.machine and args.artefact):
        raise _user_error("gap: --log (or --centres), --machine and --artefact are required "
                          "(or --selfcheck)")
    if args.log and args.centres:
        raise _user_error("gap: --log or --centres, not both")
    machine, mfile = load_machine(args.machine)
    artefact = load_artefact(args.artefact)
    stylus_r = (args.stylus_diameter_mm or DEFAULT_STYLUS_DIAMETER_MM) / 2
    known = _known(args.known, machine, artefact, mfile.gravity)
    stated = parse_repeatability(args.repeatability_um)
    opts = Options(families=_families(args.families), split=args.split,
                   known=[(e, None) for e in known], gravity_dir=mfile.gravity,
                   repeatability_um=stated,
                   rotary_repeatability_urad=mfile.rotary_repeatability_urad,
                   visit_scatter=not args.no_visit_scatter)
    try:
        if args.centres:
            poses = [(p.b_deg, p.c_deg) for p in load_plan(args.plan).poses] \
                if args.plan else None

            def read(path: str) -> centres_input.CentresInput:
                return centres_input.load(path, args.format, machine, artefact, ball=args.ball,
                                          plan_poses=poses, repeatability_um=stated)

            train_c = read(args.centres)
            for w in train_c.warnings:
                print(f"warning: {w}")
            hold_c = read(args.holdout) if args.holdout else None
            _plan_warnings(machine, train_c.indexations,
                           None if hold_c is None else hold_c.indexations)
            rep = centres_input.diagnose_gap(machine, train_c, hold_c, opts)
        else:
            train = _load(args.log, artefact)
            hold = _load(args.holdout, artefact) if args.holdout else None
            _plan_warnings(machine, _indexations(train),
                           None if hold is None else _indexations(hold))
            rep = diagnose(machine, artefact, train, stylus_r, hold, opts)
    except ProbeLogError as e:
        raise _user_error(str(e)) from None
    except ValueError as e:  # data that cannot support a diagnosis (e.g. too few poses)
        raise _user_error(f"{args.log or args.centres}: {e}") from None
    _print_report(rep)
    if args.json:
        _write(args.json, json.dumps(rep, indent=1), "--json")
        print(f"wrote {args.json}")
    if args.html:
        from daemon.reports.gap import render

        _write(args.html, render(rep, title=f"Gap diagnosis — {args.log}"), "--html")
        print(f"wrote {args.html}")
    return 0
