"""`rumba analyze`: setup + link errors from a probing log or measured centres, printed and JSON."""

from __future__ import annotations

import argparse
import json
import warnings
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from rich.console import Console
from rich.table import Table

from contracts.probing_log import ProbeLogError, read_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis.identify import (
    AnalysisError,
    ImplausibleFitError,
    analyse_centres,
    fitting_machines,
)
from daemon.analysis.result import Analysis
from daemon.analysis.touch_centres import rows_to_centres
from daemon.cli.arguments import parse_poses, parse_repeatability
from daemon.cli.choices import DEFAULT_STYLUS_DIAMETER_MM
from daemon.cli.tables import print_long_table
from daemon.reports.index_scatter import index_scatter_lines

if TYPE_CHECKING:  # the centres path's modules are imported when it runs
    from daemon.analysis.centres_shape import OneIndexation


def _user_error(msg: str) -> Exception:
    from daemon.cli.main import UserError  # late import: only on an error

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


def run_analysis(log: Path | str, machine_path: Path | str, artefact_path: Path | str,
                 validate_poses: Sequence[int] = (), links: str = "all",
                 fixed_radius: bool = False,
                 stylus_diameter_mm: float = DEFAULT_STYLUS_DIAMETER_MM,
                 repeatability_um: Sequence[float] | None = None,
                 keep: dict[str, Any] | None = None) -> Analysis:
    """Read ``log`` and analyse it (``daemon.analysis.identify.analyse_centres``; ``keep``
    receives what that keeps: the estimate, the centres in its frame)."""
    machine, mfile = load_machine(machine_path)
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
                              fixed_radius=fixed_radius, source=str(log),
                              rotary_repeatability_urad=mfile.rotary_repeatability_urad,
                              keep=keep)
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
    from daemon.analysis import centres_input  # imports scipy (gap): only for centres

    if args.fixed_radius:
        raise _user_error("--fixed-radius: centres carry no touches to fit")
    machine, mfile = load_machine(args.machine)
    artefact = load_artefact(args.artefact)
    poses = None
    if args.plan:
        poses = [(p.b_deg, p.c_deg) for p in load_plan(args.plan).poses]
    return centres_input.run(
        args.centres, machine, artefact, fmt=args.format, frame=args.frame, ball=args.ball,
        plan_poses=poses, validate_poses=parse_poses(args.validate_poses),
        links=parse_links(args.links, machine.location_error_names()),
        repeatability_um=parse_repeatability(args.repeatability_um),
        rotary_repeatability_urad=mfile.rotary_repeatability_urad)


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
    sf = e.sphere_frame
    if sf is not None:
        t.add_row("sphere fits in the estimate's frame",
                  sf.note or f"centres moved ≤ {sf.max_shift_um:.3f} µm ({sf.passes} pass"
                  f"{'' if sf.passes == 1 else 'es'})")
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
    bc = {(v.pose, v.repeat): (v.b_deg, v.c_deg) for v in r.volumetric}
    cluster = []
    for x in r.cluster:
        b, c = bc[(x.pose, x.repeat)]
        loc = max(np.linalg.norm(v) for v in x.local_um.values())  # type: ignore[arg-type]
        pose = str(x.pose) + (f" r{x.repeat}" if x.repeat else "")
        cluster.append((pose, f"{b:g}", f"{c:g}", _norm(x.linear_um), _norm(x.angular_urad),
                        f"{loc:.2f}"))
    print_long_table(console, "Cluster analysis per pose (setup-only prediction)",
                     [(hd, "right") for hd in ("pose", "b°", "c°", "|relocalisation| µm",
                                               "|rotation| µrad", "max local µm")], cluster)
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
    for line in index_scatter_lines(r):  # the report's text; warnings just below
        if not line.startswith("Warning: "):
            console.print(line, markup=False, highlight=False)
    for w in r.warnings:  # a faulty ball visit (touch_centres.screen_centres) in red
        bad = w.startswith("measurement outlier")
        console.print(f"{'[bold red]' if bad else '[yellow]'}warning:[/] {w}")


def cmd_analyze(args: argparse.Namespace) -> int:
    """`rumba analyze` (``daemon.cli.parsers.analyze``): analyse, print, write the files."""
    keep: dict[str, Any] = {}
    if args.centres:
        result = _centres(args)
    else:
        result = run_analysis(args.log, args.machine, args.artefact,
                              parse_poses(args.validate_poses), args.links, args.fixed_radius,
                              args.stylus_diameter, parse_repeatability(args.repeatability_um),
                              keep)
    if isinstance(result, Analysis):
        render(result, Console())
    else:
        from daemon.analysis.centres_shape import render as render_one_indexation

        render_one_indexation(result, Console())
    if args.write_centres:
        if not args.log:
            raise _user_error("--write-centres: needs --log (the centres of its touches)")
        from daemon.analysis import centres_input

        n = centres_input.export_log_centres(args.log, load_artefact(args.artefact),
                                             args.stylus_diameter / 2, args.fixed_radius,
                                             args.write_centres, keep.get("touch_data"))
        print(f"wrote {n} centres to {args.write_centres}")
    if args.json:
        try:
            Path(args.json).write_text(
                json.dumps(result.to_json(), indent=1, ensure_ascii=False) + "\n",
                encoding="utf-8")
        except OSError as e:
            raise _user_error(f"--json {args.json}: cannot write: {e.strerror}") from None
        print(f"wrote {args.json}")
    return 0
