"""A run's report job in the journal (migration 10): writing → written | failed, with its reason.

The report is rendered after the run's end (daemon/run/report_job.py): the run's row
says how the run ended, this one how its report did — a report that could not be written no
longer rewrites the run's reason. Every surface that links to a report (HMI, fleet page, OPC UA
results, notifications, ``rumba verify``) reads it here, or the fleet store's copy.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from daemon.store.journal import Store, validate_run_id

WRITING, WRITTEN, FAILED = "writing", "written", "failed"
STATES = (WRITING, WRITTEN, FAILED)
REASON_CHARS = 300  # a reason is one line for a card or a table cell, not a traceback
ABANDONED = "the daemon stopped unexpectedly while it was being written"


@dataclass(frozen=True)
class ReportJob:
    """One row of ``report_jobs``."""

    run_id: str
    state: str  # writing | written | failed
    reason: str  # why it failed ('' otherwise)
    started_at: float
    ended_at: float | None

    @property
    def ended(self) -> bool:
        return self.state != WRITING


def begin(store: Store, run_id: str) -> None:
    """The run's report is being written (a new job replaces an earlier one of the run)."""
    validate_run_id(run_id)
    store.db.execute("INSERT OR REPLACE INTO report_jobs (run_id, state, reason, started_at,"
                     " ended_at) VALUES (?, ?, '', ?, NULL)", (run_id, WRITING, time.time()))


def written(store: Store, run_id: str, html_path: Path, json_path: Path) -> None:
    """The report's files are there: their paths and the job's end, in one transaction."""
    validate_run_id(run_id)
    with store.transaction():
        store.save_report(run_id, html_path, json_path)
        _end(store, run_id, WRITTEN, "")


def failed(store: Store, run_id: str, reason: str) -> None:
    """The report was not written, and why (the run and its verdict stay as they are)."""
    validate_run_id(run_id)
    _end(store, run_id, FAILED, " ".join(reason.split())[:REASON_CHARS])


def _end(store: Store, run_id: str, state: str, reason: str) -> None:
    now = time.time()
    store.db.execute("INSERT INTO report_jobs (run_id, state, reason, started_at, ended_at)"
                     " VALUES (?, ?, ?, ?, ?) ON CONFLICT(run_id) DO UPDATE SET"
                     " state=excluded.state, reason=excluded.reason, ended_at=excluded.ended_at",
                     (run_id, state, reason, now, now))


def get(store: Store, run_id: str) -> ReportJob | None:
    """The run's report job; None when it had none (a run without a verdict, an import)."""
    validate_run_id(run_id)
    row = store.db.execute("SELECT run_id, state, reason, started_at, ended_at FROM"
                           " report_jobs WHERE run_id=?", (run_id,)).fetchone()
    return ReportJob(*row) if row else None


def mark_abandoned(store: Store) -> list[str]:
    """Jobs a crash left 'writing' → failed, saying so (at the daemon's start, as
    ``Store.mark_interrupted`` does for runs): no report stays "being written" forever."""
    ids = [r[0] for r in store.db.execute("SELECT run_id FROM report_jobs WHERE state=?",
                                          (WRITING,))]
    for run_id in ids:
        failed(store, run_id, ABANDONED)
    return ids
