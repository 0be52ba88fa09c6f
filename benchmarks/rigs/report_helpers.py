"""Journal a run the way the session does, for the report, trend and browser tests."""

from __future__ import annotations

import dataclasses

from benchmarks.rigs.daemon_helpers import thesis_rows
from daemon.analysis import pipeline
from daemon.analysis.judge import Judgement, judge
from daemon.store.journal import Store


def journal_run(store: Store, setup, run_id: str, seed: int, started: float,
                reason: str = "") -> tuple[pipeline.RunAnalysis, Judgement]:
    """Journal one run like the session does; returns its analysis and judgement."""
    rows = thesis_rows(setup, seed=seed)
    hits = [pipeline.row_to_hit(r, setup.machine) for r in rows]
    store.new_run(run_id, setup.name, "cnc", plan=setup.plan.name, started_at=started)
    store.journal_hits(run_id, hits)
    a = pipeline.analyse(setup, hits, run_id)
    store.save_centres(run_id, a.centre_rows)
    store.save_analysis(run_id, a.data)
    j = judge(a.data, setup.tolerances)
    if reason:
        j = dataclasses.replace(j, reasons=(*j.reasons, reason))
    store.save_verdict(run_id, j.status, list(j.reasons), [c.as_dict() for c in j.checks],
                       j.summary)
    store.set_state(run_id, "DONE")
    return a, j
