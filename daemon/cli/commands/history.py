"""``rumba history``: list runs and trends of the journal; export a run to the probing-log CSV
(``--export RUN --csv OUT``) or import one (``--import CSV --machine NAME``, then analysed,
judged and reported like a live run)."""

from __future__ import annotations

import argparse
import sqlite3
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from contracts.messages import ProbeHit
from contracts.probing_log import ProbeLogError
from daemon.analysis.figures import DEFINITIONS, LABELS, VOLUMETRIC
from daemon.analysis.judge import Judgement, judge, volumetric_max_um
from daemon.analysis.pipeline import PipelineError, RunAnalysis, analyse, row_to_hit
from daemon.cli.main import UserError
from daemon.compensation.propose import ControllerModelError, controller_model
from daemon.config import DaemonConfig, load_daemon_config
from daemon.machines.setup import MachineSetup
from daemon.reports.compensation import verification_of
from daemon.store import baselines, map_results, report_jobs
from daemon.store.journal import Store, StoreError
from daemon.store.probing_csv import export_csv, journal_import, read_import

# What bad data (absurd coordinates, degenerate ball-poses …) makes the analysis raise; the
# import then stops with one line and journals nothing.

STYLE = {"PASS": "green", "WARN": "yellow", "FAIL": "red"}


def _open(cfg: DaemonConfig) -> Store:
    try:
        return Store(cfg.store_path, cfg.synchronous,  # type: ignore[arg-type]
                     source=f"{cfg.path}: store.path")
    except StoreError as e:
        raise UserError(str(e)) from None


def cmd_history(args: argparse.Namespace) -> int:
    cfg = load_daemon_config(args.config)
    if args.machine is not None and args.machine not in cfg.machines:
        raise UserError(f"{args.config}: no machine {args.machine!r} "
                        f"(configured: {', '.join(cfg.machines)})")
    store = _open(cfg)
    try:
        if args.export:
            return _export(cfg, store, args)
        if args.import_csv:
            return _import(cfg, store, args)
        if getattr(args, "export_aqdef", None):
            return _export_aqdef(cfg, store, args)
        if getattr(args, "against_temperature", None):
            from daemon.cli.commands.temperature_trend import cmd_against_temperature

            return cmd_against_temperature(cfg, store, args)
        _list(store, args.machine, args.limit)
        return 0
    finally:
        store.close()


def _export(cfg: DaemonConfig, store: Store, args: argparse.Namespace) -> int:
    if map_results.find(store, args.export) is not None:
        return _export_map(store, args)
    if args.json:
        raise UserError(f"--json OUT exports a map result; {args.export} is not one (a run: "
                        "--csv OUT)")
    if not args.csv:
        raise UserError("--export needs --csv OUT")
    try:
        run = store.run(args.export)
        n = export_csv(store, args.export, args.csv, cfg.machines[run.machine].machine
                       if run.machine in cfg.machines else _unknown(run.machine, args.config))
    except (StoreError, PipelineError, OSError) as e:
        raise UserError(str(e)) from None
    print(f"{args.csv}: {n} touches of run {args.export}")
    return 0


def _export_map(store: Store, args: argparse.Namespace) -> int:
    """A map result: its map file as journaled (SHA-256 checked) to --json OUT."""
    if not args.json:
        raise UserError(f"{args.export} is a map result (no touches of its own): --export "
                        f"{args.export} --json OUT writes its map file")
    try:
        m = map_results.export_map(store, args.export, args.json)
    except StoreError as e:
        raise UserError(str(e)) from None
    print(f"{args.json}: map {m.id} of {m.machine} ({m.describe()})")
    return 0


def _export_aqdef(cfg: DaemonConfig, store: Store, args: argparse.Namespace) -> int:
    """One machine per file (one AQDEF part): --machine, or the only one configured."""
    from daemon.reports.aqdef import write_aqdef

    if args.machine is None and len(cfg.machines) != 1:
        raise UserError(f"--export-aqdef: name the machine with --machine (configured: "
                        f"{', '.join(cfg.machines)})")
    setup = cfg.machines[args.machine or next(iter(cfg.machines))]
    runs = store.trend(setup.name, limit=1_000_000)  # completed runs, oldest first
    maps = map_results.listed(store, setup.name, 1_000_000)[::-1]  # oldest first
    try:
        n = write_aqdef(args.export_aqdef, setup.name, runs, setup.tolerances,
                        operator=setup.operator, artefact=setup.artefact.name, maps=maps)
    except OSError as e:
        raise UserError(f"{args.export_aqdef}: cannot write: {e.strerror or e}") from None
    also = f" and {len(maps)} map results" if maps else ""
    print(f"wrote {args.export_aqdef}: {n} runs{also} of {setup.name} (AQDEF)")
    return 0


def _unknown(machine: str, config: str) -> None:
    raise UserError(f"run belongs to machine {machine!r}, not configured in {config}")


def _import(cfg: DaemonConfig, store: Store, args: argparse.Namespace) -> int:
    """All or nothing: the log is read, checked, analysed and judged first, then the run, its
    hits and its results are committed in one transaction. A bad row or a failed analysis
    leaves the journal as it was, so the corrected file imports."""
    if not args.machine:
        raise UserError("--import needs --machine NAME (whose artefact and plan the log uses)")
    setup = cfg.machines[args.machine]
    path = args.import_csv
    try:
        run_id, rows = read_import(store, path, setup.artefact)
    except (StoreError, ProbeLogError, OSError) as e:
        raise UserError(str(e)) from None
    hits = [row_to_hit(r, setup.machine) for r in rows]
    result = None if args.no_analyse else _analyse(setup, store, hits, run_id, path)
    try:
        with store.transaction():
            n = journal_import(store, run_id, hits, setup.name, setup.artefact)
            if result is not None:
                a, j = result
                store.save_centres(run_id, a.centre_rows)
                store.save_analysis(run_id, a.data)
                store.save_judgement(run_id, j)
                store.set_state(run_id, "DONE")
    except sqlite3.IntegrityError as e:
        raise UserError(f"{path}: run {run_id} refused by the journal ({e}: two rows with "
                        "the same seq?); nothing imported") from None
    except (StoreError, sqlite3.Error) as e:
        raise UserError(f"{path}: run {run_id} not imported: {e}") from None
    print(f"imported run {run_id}: {n} touches")
    if result is None:
        return 0
    from daemon.reports import report
    a, j = result
    run, trend = store.run(run_id), store.trend(setup.name)  # as committed: state DONE
    try:  # after the commit: rendering takes seconds, the daemon must not wait on the journal
        html, json_path = report.write_report(
            cfg.reports_dir, run, a.data, j, a.centre_rows, trend, setup.tolerances,
            report.audit_of(setup), verification_of(store, run, a.data, setup))
        report_jobs.written(store, run_id, html, json_path)
    except OSError as e:
        report_jobs.failed(store, run_id, f"{type(e).__name__}: {e.strerror or e}")
        raise UserError(f"run {run_id} imported ({j.summary}), but its report cannot be "
                        f"written in {cfg.reports_dir}: {e.strerror or e}") from None
    # every file written, the HTML last on its own "report:" line (scripts read it from there)
    print(f"{j.summary}\nwrote {json_path}\nwrote {report.pdf_path(html)}\nreport: {html}")
    return 0


def _analyse(setup: MachineSetup, store: Store, hits: list[ProbeHit], run_id: str,
             path: str | Path) -> tuple[RunAnalysis, Judgement]:
    # judged and recorded like a live run: against the machine's baseline
    base = baselines.reference(store, setup.name, before=run_id)
    ref = (base[0].run_id, base[1]) if base else None
    try:
        # an import of old data never reads a live machine: the journal's model,
        # not the HAL pins of whatever LinuxCNC happens to run on this PC
        model = controller_model(setup, store, check_hal=False)
        a = analyse(setup, hits, run_id, ref, controller=model)
    except ControllerModelError as e:
        raise UserError(f"{path}: run {run_id}: {e}") from None
    except PipelineError as e:
        raise UserError(f"{path}: run {run_id}: analysis failed: {e}; nothing imported (use "
                        "--no-analyse to journal the touches anyway)") from None
    return a, judge(a.data, setup.tolerances, ref[1] if ref else None)


def _list(store: Store, machine: str | None, limit: int) -> None:
    console = Console()
    if not console.is_terminal:
        console = Console(width=200)  # piped output: do not squeeze the tables to 80 columns
    t = Table(title="Runs (most recent first)")
    for h in ("started", "run", "machine", "trigger", "state", "verdict", "touches",
              f"{LABELS[VOLUMETRIC]} µm", "reason / summary"):
        t.add_column(h)
    for r in store.runs(machine, limit):
        a = store.analysis(r.id)
        vmax = volumetric_max_um(a) if a else None
        job = report_jobs.get(store, r.id)  # the report's end is its job's, not the run's
        why = (f"; report not written: {job.reason}" if job and job.state == "failed"
               and "report not written" not in r.reason else "")
        t.add_row(time.strftime("%Y-%m-%d %H:%M", time.localtime(r.started_at)), r.id,
                  r.machine, r.trigger, r.state,
                  f"[{STYLE.get(r.verdict or '', 'white')}]{r.verdict or '—'}[/]",
                  f"{r.hits}/{r.touch_total}", "—" if vmax is None else f"{vmax:.1f}",
                  (r.reason or r.summary) + why)
    console.print(t)
    _list_maps(console, store, machine, limit)
    # the figure's definition beside it, and each machine's drift baseline
    console.print(f"{LABELS[VOLUMETRIC]}: {DEFINITIONS[VOLUMETRIC]}.", soft_wrap=True,
                  markup=False, highlight=False)
    machines = [machine] if machine else sorted({r.machine for r in store.runs(None, 500)})
    for m in machines:
        b = baselines.current(store, m)
        console.print(f"{m}: drift judged against baseline {b.describe()}" if b else
                      f"{m}: drift not checked: no baseline", soft_wrap=True, markup=False,
                      highlight=False)
    for m in machines:
        trend = store.trend(m, limit)
        if len(trend) < 2:
            continue
        names = sorted({n for x in trend for n in x.analysis.links})
        tt = Table(title=f"Trend of {m} (oldest first; µrad / µm)")
        tt.add_column("run")
        tt.add_column("verdict")
        for n in names:
            tt.add_column(n, justify="right")
        tt.add_column("max vol. dist. (probed poses)", justify="right")
        for x in trend:
            links = x.analysis.links
            v = volumetric_max_um(x.analysis)
            tt.add_row(x.run_id, x.verdict,
                       *(f"{links[n].value:+.1f}" if n in links else "—" for n in names),
                       "—" if v is None else f"{v:.1f}")
        console.print(tt)


def _list_maps(console: Console, store: Store, machine: str | None, limit: int) -> None:
    """The map results (kind map), newest first: their figures over the covered box, verdict,
    what is not observable and where their report is."""
    maps = map_results.listed(store, machine, limit)
    if not maps:
        return
    t = Table(title="Map results of the linear axes (kind map, most recent first)")
    for h in ("recorded", "map", "kind", "machine", "placements", "covered mm",
              "vol. max ± u µm", "vol. RMS µm", "verdict", "not observable", "report"):
        t.add_column(h)
    for m in maps:
        f = m.figures
        covered = " ".join(f"{a} {lo:g}..{hi:g}" for a, (lo, hi) in f["covered_mm"].items())
        u = "" if m.volumetric_max_u_um is None else f" ± {m.volumetric_max_u_um:.1f}"
        verdict = (f"[{STYLE.get(m.verdict, 'white')}]{m.verdict}[/]" if m.verdict
                   else "not judged")
        t.add_row(time.strftime("%Y-%m-%d %H:%M", time.localtime(m.created_at)), m.id,
                  m.kind, m.machine, str(m.placements), covered,
                  f"{m.volumetric_max_um:.1f}{u}", f"{m.volumetric_rms_um:.1f}", verdict,
                  ", ".join(f["unobservable"]) or "—", m.report_html or m.json_path)
    console.print(t)
