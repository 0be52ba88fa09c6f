"""`rumba analyze`: identify setup + link errors from a probing log or measured centres, print a
summary, write JSON."""

from __future__ import annotations

import argparse
import json
import warnings
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from contracts.centres_file import FRAMES
from contracts.importers import FORMATS
from contracts.probing_log import ProbeLogError, read_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis import centres_input
from daemon.analysis.centres_shape import OneIndexation
from daemon.analysis.centres_shape import render as render_one_indexation
from daemon.analysis.identify import (
    AnalysisError,
    ImplausibleFitError,
    analyse_centres,
    fitting_machines,
)
from daemon.analysis.result import Analysis
from daemon.analysis.touch_centres import rows_to_centres

DEFAULT_STYLUS_DIAMETER_MM = 6.0  # the shipped plans' stylus; used for the radius health figure

def _user_error(msg: str) -> Exception:
    from daemon.cli.main import UserError  # late import: cli imports every command module

    return UserError(msg)


def parse_links(text: str, candidates: Sequence[str]) -> tuple[str, ...] | None:
    """``all`` → None (the identifiable set), ``none`` → (), else a comma list of ISO names."""
    t = text.strip()
    if t.lower() == "all":
        return None
    if t.lower() == "none":
        return ()
    names = tuple(n.strip().upper() for n in t.split(",") if n.strip())
    bad = [n for n in names if n not in candidates]
    if bad or not names:
        raise _user_error(f"--links: unknown link error(s) {bad or [text]}; this machine has "
                          f"{', '.join(candidates)} (or 'all' / 'none')")
    return names


def parse_poses(text: str | None) -> list[int]:
    if not text:
        return []
    try:
        return sorted({int(x) for x in text.split(",") if x.strip()})
    except ValueError:
        raise _user_error(f"--validate-poses: expected a comma list of pose numbers as in the "
                          f"log's pose column, got {text!r}") from None


def parse_repeatability(text: str | None) -> list[float] | None:
    if not text:
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) not in (1, 3) or not all(np.isfinite(x) and x > 0 for x in v):
        raise _user_error(f"--repeatability-um: expected one or three positive numbers "
                          f"(x,y,z centre std in µm), got {text!r}")
    return v * 3 if len(v) == 1 else v


def run_analysis(log: Path | str, machine_path: Path | str, artefact_path: Path | str,
                 validate_poses: Sequence[int] = (), links: str = "all",
                 fixed_radius: bool = False,
                 stylus_diameter_mm: float = DEFAULT_STYLUS_DIAMETER_MM,
                 repeatability_um: Sequence[float] | None = None) -> Analysis:
    """Read ``log`` and analyse it (``daemon.analysis.identify.analyse_centres``)."""
    machine, _ = load_machine(machine_path)
    artefact = load_artefact(artefact_path)
    chosen = parse_links(links, machine.location_error_names())
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")  # the reader's (seq gaps) go into the JSON too
            rows = read_log(log, artefact)
        read_warnings = [str(w.message) for w in caught]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # returned in data.warnings and reported below
            data = rows_to_centres(rows, artefact, stylus_diameter_mm / 2, fixed_radius,
                                   source=str(log))
        out = analyse_centres(machine, artefact, data, validate_poses=validate_poses,
                              links=chosen, repeatability_um=repeatability_um,
                              fixed_radius=fixed_radius, source=str(log))
    except ImplausibleFitError as e:
        raise _user_error(f"{e}{_taken_on(machine_path, artefact, data.centres)}") from None
    except (ProbeLogError, AnalysisError) as e:
        raise _user_error(str(e)) from None
    return replace(out, log=str(log), warnings=(*read_warnings, *out.warnings))


MAX_SIBLINGS = 8  # machine files tried for the hint (about 0.5 s each, on the error path only)


def _taken_on(machine_path: Path | str, artefact: Any, centres: Any) -> str:
    """The hint of an implausible fit: the other machine files next to ``machine_path`` the
    log does fit (the machine it was probably taken on), '' when none does."""
    here = Path(machine_path)
    try:
        others = sorted(p for p in here.parent.glob("*.yaml") if p.resolve() != here.resolve())
    except OSError:
        return ""
    fits = fitting_machines(others[:MAX_SIBLINGS], artefact, centres)
    return f" The log fits {', '.join(map(str, fits))}: taken on that machine?" if fits else ""


def _centres(args: argparse.Namespace) -> Analysis | OneIndexation:
    """``--centres``: read or import the file, then ``daemon.analysis.centres_input.run``."""
    if args.fixed_radius:
        raise _user_error("--fixed-radius: centres carry no touches to fit")
    machine, _ = load_machine(args.machine)
    artefact = load_artefact(args.artefact)
    poses = None
    if args.plan:
        poses = [(p.b_deg, p.c_deg) for p in load_plan(args.plan).poses]
    return centres_input.run(
        args.centres, machine, artefact, fmt=args.format, frame=args.frame, ball=args.ball,
        plan_poses=poses, validate_poses=parse_poses(args.validate_poses),
        links=parse_links(args.links, machine.location_error_names()),
        repeatability_um=parse_repeatability(args.repeatability_um))


def _norm(v: Sequence[float | None] | None) -> str:
    return "—" if v is None else f"{np.linalg.norm(v):.2f}"  # type: ignore[arg-type]


def render(r: Analysis, console: Console) -> None:
    """The readable summary (rich tables, units everywhere)."""
    e = r.estimation
    assert e is not None and r.setup is not None and r.volumetric_max_um is not None
    console.print(f"[bold]RUMBA analysis[/] of {r.log} — machine {r.machine}, artefact "
                  f"{r.artefact}: {e.centres} centres, {e.status} in "
                  f"{e.iterations} iterations")
    t = Table(title="Link errors (ISO 230-1)")
    for h in ("ISO", "thesis", "value", "± std", "unit"):
        t.add_column(h, justify="right" if h in ("value", "± std") else "left")
    for k, v in r.links.items():
        t.add_row(k, v.thesis_name, f"{v.value:.2f}", f"{v.std:.2f}",
                  "µrad" if v.unit == "urad" else "µm")
    if r.links:
        console.print(t)
    else:
        console.print("Link errors: none estimated (setup errors only, thesis ch. 3)")
    t = Table(title="Setup errors (µm)")
    for h in ("", "dx", "dy", "dz", "± std x", "± std y", "± std z"):
        t.add_column(h, justify="right")
    rows = [("probe", r.setup.probe), *r.setup.balls.items()]
    for name, s in rows:
        t.add_row(name, *(f"{x:.2f}" for x in s.value), *(f"{x:.2f}" for x in s.std))
    console.print(t)
    t = Table(title="Fit")
    t.add_column("figure")
    t.add_column("value", justify="right")
    t.add_row("residual RMS", f"{r.residual_rms_um:.3f} µm")
    t.add_row("centre std used", " / ".join(f"{x:.3f}" for x in e.sigma_um)
              + f" µm ({e.sigma_from})")
    t.add_row("condition number (normalised)", f"{r.condition_number:.1f}")
    if r.scale_um_per_m is not None:
        sc = r.scale_um_per_m
        t.add_row("isotropic scale", f"{sc.value:.2f} ± {sc.std:.2f} µm/m")
    vm = r.volumetric_max_um
    t.add_row("max volumetric distortion, setup only", f"{vm.before_links:.2f} µm")
    t.add_row("max volumetric distortion, with links", f"{vm.after_links:.2f} µm")
    h = r.health
    if h:  # no sphere fits when the input is centres (``--centres``)
        t.add_row("max |radius deviation|",
                  f"{max(abs(x.radius_dev_um) for x in h):.2f} µm")  # type: ignore[arg-type]
        t.add_row("max form residual RMS",
                  f"{max(x.form_rms_um for x in h):.2f} µm")  # type: ignore[type-var]
    console.print(t)
    if r.measured_by:
        console.print(f"Centres measured by: {r.measured_by}")
    fr = r.instrument_frame
    if fr is not None:
        console.print("Instrument frame (instrument ← machine): rotation vector "
                      f"{', '.join(f'{x:.6f}' for x in fr.rotation_vector_deg)} °, translation "
                      f"{', '.join(f'{x:.4f}' for x in fr.translation_mm)} mm; ± "
                      + ", ".join(f"{k} {'held' if v is None else f'{v:.2f}'}"
                                  for k, v in fr.std.items()) + " (µm, µrad)")
    t = Table(title="Not observable")
    t.add_column("direction")
    t.add_column("absorbed by")
    for u in r.unobservable:
        t.add_row(u, r.unobservable_absorbed_by.get(u, ""))
    console.print(t)
    t = Table(title="Cluster analysis per pose (setup-only prediction)")
    for hd in ("pose", "b°", "c°", "|relocalisation| µm", "|rotation| µrad", "max local µm"):
        t.add_column(hd, justify="right")
    bc = {(v.pose, v.repeat): (v.b_deg, v.c_deg) for v in r.volumetric}
    for x in r.cluster:
        b, c = bc[(x.pose, x.repeat)]
        loc = max(np.linalg.norm(v) for v in x.local_um.values())  # type: ignore[arg-type]
        pose = str(x.pose) + (f" r{x.repeat}" if x.repeat else "")
        t.add_row(pose, f"{b:g}", f"{c:g}", _norm(x.linear_um), _norm(x.angular_urad),
                  f"{loc:.2f}")
    console.print(t)
    v = r.validation
    if v is not None:
        ef, efr = v.explained_fraction or 0.0, v.explained_fraction_rms or 0.0
        console.print(
            f"[bold]Validation[/] on poses {list(v.poses)}: max |ε| {v.max_before_um:.2f} → "
            f"{v.max_after_um:.2f} µm, RMS {v.rms_before_um:.2f} → "
            f"{v.rms_after_um:.2f} µm; link errors explain "
            f"{100 * ef:.1f} % (max) / {100 * efr:.1f} % (RMS)")
    st = r.stability
    if st is not None:
        span = f" over {st.span_min:.1f} min" if st.span_min is not None else ""
        console.print(
            f"[bold]Stability[/] (poses probed again): largest ball-centre shift "
            f"{st.max_shift_um:.2f} µm{span} (ball {st.worst.ball}, pose {st.worst.pose})")
    for w in r.warnings:  # a faulty ball visit (touch_centres.screen_centres) in red
        bad = w.startswith("measurement outlier")
        console.print(f"{'[bold red]' if bad else '[yellow]'}warning:[/] {w}")


def _cmd(args: argparse.Namespace) -> int:
    if args.centres:
        result = _centres(args)
    else:
        result = run_analysis(args.log, args.machine, args.artefact,
                              parse_poses(args.validate_poses), args.links, args.fixed_radius,
                              args.stylus_diameter, parse_repeatability(args.repeatability_um))
    if isinstance(result, Analysis):
        render(result, Console())
    else:
        render_one_indexation(result, Console())
    if args.write_centres:
        if not args.log:
            raise _user_error("--write-centres: needs --log (the centres of its touches)")
        n = centres_input.export_log_centres(args.log, load_artefact(args.artefact),
                                             args.stylus_diameter / 2, args.fixed_radius,
                                             args.write_centres)
        print(f"wrote {n} centres to {args.write_centres}")
    if args.json:
        try:
            Path(args.json).write_text(
                json.dumps(result.to_json(), indent=1, ensure_ascii=False) + "\n",
                encoding="utf-8")
        except OSError as e:
            raise _user_error(f"--json {args.json}: cannot write: {e.strerror}") from None
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("analyze", help="identify setup and link errors from a probing log",
                              description=__doc__)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--log", help="probing-log CSV (rumba-probing-log v1)")
    src.add_argument("--centres", metavar="FILE", help="measured ball centres: a centres CSV "
                     "(rumba-centres v1) or an instrument's file (--format)")
    p.add_argument("--format", default="auto", choices=FORMATS,
                   help="--centres file format (default: told from the file)")
    p.add_argument("--frame", default=None, choices=FRAMES,
                   help="--centres: frame of the centres (default: the file's; instrument = "
                        "a rigid motion of the machine axes, estimated with the setup)")
    p.add_argument("--ball", default=None, help="--centres kinopt: the ball the program measured")
    p.add_argument("--plan", default=None, metavar="PLAN.yaml",
                   help="--centres dmis: the plan whose pose numbers the feature labels use")
    p.add_argument("--machine", required=True, help="machine YAML")
    p.add_argument("--artefact", required=True, help="artefact YAML")
    p.add_argument("--validate-poses", default=None, metavar="LIST",
                   help="comma list of pose numbers (log's pose column) held out for validation")
    p.add_argument("--links", default="all", metavar="all|none|LIST",
                   help="link errors to estimate: the identifiable set (all), none (setup only) "
                        "or a comma list of ISO names")
    p.add_argument("--fixed-radius", action="store_true",
                   help="fit spheres with radius = ball + stylus radius (default: free radius)")
    p.add_argument("--stylus-diameter", type=float, default=DEFAULT_STYLUS_DIAMETER_MM,
                   metavar="MM", help="stylus diameter for the radius health figure and "
                   f"--fixed-radius (default {DEFAULT_STYLUS_DIAMETER_MM})")
    p.add_argument("--repeatability-um", default=None, metavar="S|SX,SY,SZ",
                   help="probing repeatability of a centre (µm) for the uncertainties, e.g. "
                        "0.66,0.98,0.44 (thesis §3.4); default: from the residuals")
    p.add_argument("--json", default=None, metavar="OUT.json", help="write the results as JSON")
    p.add_argument("--write-centres", default=None, metavar="OUT.csv",
                   help="--log: also write its centres (sphere fits) as a centres CSV")
    p.set_defaults(func=_cmd)
