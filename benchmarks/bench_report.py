"""Time to write one run's report: plots, HTML + JSON, PDF, and the whole write."""

# .venv/bin/python -m benchmarks.bench_report [--runs 3] [--trend 10] [--plan shift_start_14poses]
#                                             [--profile]
#
# The report the session writes after a run (``report.write_report``): ``--trend`` journaled
# runs of the thesis machine (the last one reported, with the others as its trend), the shift-
# start plan of the shipped daemon.yaml (14 poses with its drift-check repeat). Median and best
# of ``--runs`` writes in this process, after one untimed warm-up (matplotlib's font cache and
# imports are paid once per daemon, not per run). The parts are timed on their own: the four
# plots, the HTML page (template + JSON document, the plots given), the PDF (its two pages,
# the plots given) and the whole ``write_report``. Target: total ≤ 2 s.
# ``--profile`` prints the top of a cProfile of one whole write instead.

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def _journal(tmp: Path, n_runs: int, plan: str) -> tuple[Any, ...]:
    from benchmarks.rigs.daemon_helpers import thesis_setup
    from benchmarks.rigs.report_helpers import journal_run
    from daemon.store.journal import Store

    setup = thesis_setup(plan=plan)
    store = Store(tmp / "j.sqlite")
    now = time.time()
    for i in range(n_runs):
        a, j = journal_run(store, setup, f"R{i}", i, now - (n_runs - i) * 86400)
    run_id = f"R{n_runs - 1}"
    return store, setup, store.run(run_id), a, j, store.trend(setup.name)


def _times(fn: Callable[[], object], runs: int) -> tuple[list[float], list[float]]:
    """Wall and CPU seconds of ``runs`` calls after a warm-up: on a shared machine the CPU
    time of this process is the steadier figure (the wall time counts others' load too)."""
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="bench_report")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--trend", type=int, default=10, help="journaled runs (trend length)")
    ap.add_argument("--plan", default="shift_start_14poses")
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args(argv if argv is not None else [])
    from daemon.reports import report
    from daemon.reports.audit import Audit
    from daemon.reports.pdf import write_pdf

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        store, setup, run, a, j, trend = _journal(tmp, args.trend, args.plan)
        tol = setup.tolerances
        centres = {(c[0], c[1]): c[4:7] for c in a.centre_rows}

        def whole() -> object:
            return report.write_report(tmp / "rep", run, a.data, j, a.centre_rows, trend, tol)

        if args.profile:
            whole()
            prof = cProfile.Profile()
            prof.runcall(whole)
            pstats.Stats(prof).sort_stats("cumulative").print_stats(35)
            store.close()
            return
        plots = report.render_plots(a.data, centres, trend, tol)
        _html, doc = report.build(run, a.data, j, a.centre_rows, trend, tol)
        parts = {
            "plots (4 PNG)": lambda: report.render_plots(a.data, centres, trend, tol),
            "HTML + JSON (incl. plots)": lambda: report.build(run, a.data, j, a.centre_rows,
                                                              trend, tol),
            "PDF (plots given)": lambda: write_pdf(tmp / "x.pdf", run, a.data, doc, Audit(),
                                                   plots),
            "total write_report": whole,
        }
        print(f"report of run {run.id}: plan {args.plan}, {len(a.centre_rows)} centres, "
              f"trend of {len(trend)} runs; {args.runs} writes after a warm-up")
        for name, fn in parts.items():
            wall, cpu = _times(fn, args.runs)
            print(f"  {name:26s} wall median {statistics.median(wall):5.2f} s, best "
                  f"{min(wall):5.2f} s; CPU median {statistics.median(cpu):5.2f} s")
        store.close()


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
