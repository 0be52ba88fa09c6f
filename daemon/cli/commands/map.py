"""`rumba map`: the map of the linear axes from placements (or a saved map), printed, written as
JSON, and asked for the volumetric error at commanded points."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from contracts.linear_map import LinearMapFile, load_map, map_model
from contracts.map_points import MapPointsError, read_points, write_predictions
from contracts.probing_log import ProbeLogError
from contracts.setup_files import load_machine
from daemon.cli.commands.analyze import parse_repeatability
from daemon.machines.tolerances import Limit
from identification.linmap.field import MapModel, OutsideCoverage, predict_field
from identification.linmap.fit import MapOptions
from identification.linmap.problem import MapError

MAX_DEGREE_CAP = 8


def _user_error(msg: str) -> Exception:
    from daemon.cli.main import UserError

    return UserError(msg)


def parse_degrees(text: str | None) -> dict[str, int] | None:
    if text is None:
        return None
    parts = text.split(",")
    if len(parts) != 3 or not all(p.strip().isdigit() for p in parts) or any(
            int(p) > MAX_DEGREE_CAP for p in parts):
        raise _user_error(f"--degrees: expected three whole numbers 0..{MAX_DEGREE_CAP} "
                          f"(degrees of X, Y, Z), got {text!r}")
    return dict(zip("XYZ", (int(p) for p in parts), strict=True))


def parse_limit(text: str | None) -> Limit | None:
    if text is None:
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) not in (1, 2) or not all(np.isfinite(x) and x > 0 for x in v) or (
            len(v) == 2 and v[0] > v[1]):
        raise _user_error(f"--limit-um: expected WARN or WARN,FAIL (µm, positive, warn ≤ "
                          f"fail), got {text!r}")
    return Limit(v[0], v[1] if len(v) == 2 else None)


def config_entry(config: str, machine_path: str) -> tuple[Any, Any]:
    """(the daemon config, the daemon.yaml entry of this machine, found by the machine's
    name): its tolerances judge the map, its name journals it."""
    from daemon.config import load_daemon_config

    machine, _ = load_machine(machine_path)
    cfg = load_daemon_config(config)
    mine = [s for s in cfg.machines.values() if s.machine.name == machine.name]
    if len(mine) != 1:
        names = ", ".join(s.name for s in mine) or "none"
        raise _user_error(f"--config {config}: {len(mine)} machine entries of {machine.name} "
                          f"({names}); expected one (or give --limit-um)")
    return cfg, mine[0]


def limit_from_config(config: str, machine_path: str) -> tuple[Limit | None, str | None, float]:
    """The volumetric limit, its stated source and the coverage k of the daemon.yaml entry
    of this machine (by the machine's name)."""
    tol = config_entry(config, machine_path)[1].tolerances
    return (tol.volumetric_max_um, tol.sources.get("volumetric_max_um"), tol.coverage_k)


def store_map(config: str, machine_path: str, map_json: str, report: str | None) -> None:
    """Journal the map written to ``map_json`` (and ``report``) in the journal of ``config``,
    under the daemon.yaml name of the machine: history, HMI, fleet store, OPC UA, AQDEF."""
    from daemon.store.journal import Store, StoreError
    from daemon.store.map_results import record_map_result

    cfg, entry = config_entry(config, machine_path)
    try:
        store = Store(cfg.store_path, cfg.synchronous, source=f"{cfg.path}: store.path")
    except StoreError as e:
        raise _user_error(f"the map is written ({map_json}) but not journaled: {e}") from None
    try:
        m = record_map_result(store, None, map_json, report, machine=entry.name,
                              recorded_by="rumba map")
    except StoreError as e:
        raise _user_error(f"the map is written ({map_json}) but not journaled: {e}") from None
    finally:
        store.close()
    print(f"journaled map {m.id} of {m.machine}: {m.describe()}")
    if cfg.aqdef_dir is not None:  # the SPC folder gets it as it gets each run's
        from daemon.service.aqdef_drop import drop_file

        try:
            path = drop_file(cfg.aqdef_dir, entry, m.id, [], [m])
        except OSError as e:
            raise _user_error(f"map {m.id} journaled, but its AQDEF file not written in "
                              f"{cfg.aqdef_dir}: {e.strerror or e}") from None
        print(f"wrote {path} (AQDEF)")


def _check_args(args: argparse.Namespace) -> None:
    if bool(args.placement) == bool(args.map):
        raise _user_error("give the placements (--placement LOG ARTEFACT, repeated) or a saved "
                          "map (--map MAP.json), one of the two")
    if args.map and (args.holdout or args.json):
        raise _user_error("--map predicts from a saved map: --holdout and --json need "
                          "--placement")
    if bool(args.predict) != bool(args.out):
        raise _user_error("--predict POINTS.csv and --out PRED.csv go together")
    if args.placement and not (args.json or args.predict or args.report):
        raise _user_error("nothing to write: give --json OUT.json, --report DIR and/or "
                          "--predict/--out")
    if args.map and not (args.predict or args.report or args.store):
        raise _user_error("--map: nothing to do: give --predict POINTS.csv --out PRED.csv, "
                          "--report DIR and/or --store")
    if args.store and not args.config:
        raise _user_error("--store journals the map in the daemon's journal: give --config "
                          "daemon.yaml (it names the journal and the machine)")
    if args.store and args.placement and not (args.json or args.report):
        raise _user_error("--store journals the map file's path and hash: give --json "
                          "OUT.json and/or --report DIR")
    if not 1 <= args.max_degree <= MAX_DEGREE_CAP:
        raise _user_error(f"--max-degree: expected 1..{MAX_DEGREE_CAP}, got {args.max_degree}")
    if args.limit_um and args.config:
        raise _user_error("--limit-um or --config, not both")
    if args.stylus_diameter is None or not 0 < args.stylus_diameter < 100:
        raise _user_error(f"--stylus-diameter: expected 0 < MM < 100, got {args.stylus_diameter}")


def predict_points(model: MapModel, points: str, out: str) -> int:
    """Read ``points``, predict, write ``out``; the number of points."""
    try:
        xyz, lines = read_points(points)
    except MapPointsError as e:
        raise _user_error(str(e)) from None
    try:
        pred = predict_field(model, xyz)
    except OutsideCoverage as e:
        lo, hi = model.box_mm[e.axis]
        raise _user_error(f"{points}: line {lines[e.index]}: column {e.axis.lower()}_mm: "
                          f"{xyz[e.index, 'XYZ'.index(e.axis)]:g} mm is outside the covered "
                          f"range {lo:g} .. {hi:g} mm of {e.axis}: the map does not "
                          "extrapolate") from None
    try:
        write_predictions(out, xyz, pred.error_um, pred.u_um)
    except OSError as e:
        raise _user_error(f"--out {out}: cannot write: {e.strerror}") from None
    return len(xyz)


def render(d: LinearMapFile, console: Console) -> None:
    t = Table(title="Placements")
    for h in ("", "log", "centres", "poses", "residual RMS µm"):
        t.add_column(h)
    for p in d.placements:
        t.add_row(p.name, p.log, str(p.centres), str(p.poses), f"{p.residual_rms_um:.3f}")
    console.print(t)
    box = ", ".join(f"{a.axis} {a.range_mm[0]:g}..{a.range_mm[1]:g} mm (degree {a.degree})"
                    for a in d.basis.axes)
    console.print(f"Covered: {box}")
    t = Table(title="Link errors (ISO 230-1)")
    for h in ("ISO", "value", "± std", "unit"):
        t.add_column(h)
    for k, v in d.links.items():
        t.add_row(k, f"{v.value:.2f}", f"{v.std:.2f}", "µrad" if v.unit == "urad" else "µm")
    console.print(t)
    t = Table(title="Motion errors over the covered range (max |e| ± u there)")
    for h in ("ISO", "terms", "max |e|", "± u", "unit"):
        t.add_column(h)
    for f in d.functions:
        if not f.terms:
            continue
        i = int(np.argmax(np.abs(f.value)))
        t.add_row(f.name, str(len(f.terms)), f"{abs(f.value[i]):.2f}", f"{f.u[i]:.2f}",
                  "µrad" if f.unit == "urad" else "µm")
    console.print(t)
    t = Table(title="Not observable")
    t.add_column("direction")
    t.add_column("absorbed by")
    for k, v in d.observability.unobservable.items():
        t.add_row(k, v)
    console.print(t)
    console.print(d.observability.note, markup=False, highlight=False)
    fig = d.figures.volumetric_max_um
    verdict = f" — {fig.status} ({fig.limit})" if fig.status else ""
    console.print(f"Volumetric error over the covered box (rigid convention): max "
                  f"{fig.value_um:.2f} ± {fig.u_um or 0:.2f} µm, RMS "
                  f"{d.figures.volumetric_rms_um:.2f} µm{verdict}", markup=False)
    console.print(f"Fit: residual RMS {d.fit.residual_rms_um:.3f} µm, "
                  f"{'converged' if d.fit.converged else 'NOT converged'}", markup=False)
    if d.holdout is not None:
        h = d.holdout
        console.print(f"Held out ({h.log}, {h.centres} centres): RMS {h.rms_before_um:.2f} → "
                      f"{h.rms_after_um:.2f} µm, max {h.max_before_um:.2f} → "
                      f"{h.max_after_um:.2f} µm without → with the map", markup=False)
    for w in d.warnings:
        console.print(f"warning: {w}", markup=False, highlight=False)


def _report_dir(report: str | None) -> None:
    """The report directory made and proven writable before the fit (minutes) runs."""
    if report is None:
        return
    from daemon.reports.map_report import check_report_dir

    try:
        check_report_dir(report)
    except OSError as e:
        raise _user_error(f"--report {report}: cannot write the report there: "
                          f"{e.strerror or e}") from None


def write_report(report: str | None, doc: LinearMapFile, model: MapModel) -> None:
    if report is None:
        return
    from daemon.reports.map_report import write_map_report  # matplotlib: only when asked

    try:
        paths = write_map_report(report, doc, model)
    except OSError as e:
        raise _user_error(f"--report {report}: cannot write the report: "
                          f"{e.strerror or e}") from None
    print(f"wrote the map report {paths['html']} (and {paths['pdf'].name}, "
          f"{paths['json'].name})")


def cmd_map(args: argparse.Namespace) -> int:
    """`rumba map` (``daemon.cli.parsers.map``)."""
    _check_args(args)
    _report_dir(args.report)
    if args.map:
        machine, _ = load_machine(args.machine)
        saved = load_map(args.map)
        model = map_model(machine, saved, args.map)
        if args.predict:
            n = predict_points(model, args.predict, args.out)
            print(f"wrote {n} predictions to {args.out}")
        write_report(args.report, saved, model)
        if args.store:
            store_map(args.config, args.machine, args.map, args.report)
        return 0
    from daemon.analysis.linear_map import run_map  # the fit's modules (scipy): when it runs

    limit, source, k = parse_limit(args.limit_um), None, 2.0
    if args.config:
        limit, source, k = limit_from_config(args.config, args.machine)
    options = MapOptions(max_degree=args.max_degree, degrees=parse_degrees(args.degrees))
    try:
        run = run_map(args.machine, [tuple(p) for p in args.placement],
                      tuple(args.holdout) if args.holdout else None,
                      stylus_radius_mm=args.stylus_diameter / 2, fixed_radius=args.fixed_radius,
                      repeatability_um=parse_repeatability(args.repeatability_um),
                      options=options, limit=limit, limit_source=source, coverage_k=k)
    except ProbeLogError as e:
        raise _user_error(str(e)) from None
    except MapError as e:  # too few poses, an axis that never moved …: the estimator says
        raise _user_error(f"map: {e}") from None
    render(run.document, Console())
    if args.json:
        try:
            Path(args.json).write_text(json.dumps(run.document.to_json(), indent=1,
                                                  ensure_ascii=False) + "\n", encoding="utf-8")
        except OSError as e:
            raise _user_error(f"--json {args.json}: cannot write: {e.strerror}") from None
        print(f"wrote {args.json}")
    if args.predict:
        n = predict_points(run.model, args.predict, args.out)
        print(f"wrote {n} predictions to {args.out}")
    write_report(args.report, run.document, run.model)
    if args.store:
        store_map(args.config, args.machine, args.json or str(Path(args.report) / "map.json"),
                  args.report)
    return 0
