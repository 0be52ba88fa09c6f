"""A run's report written off the run's critical path, in a worker thread."""

# The verdict is journaled, judged, written back to the CNC and the run's end (DONE) published
# before anything is rendered: the machine goes back to production ~2 s earlier (plots and PDF
# take 2.2 s of CPU, more on a loaded shop PC). The rendering then runs in a thread; the job is
# journaled apart from the run (``report_jobs``, daemon/store/report_jobs.py: writing → written
# with the ``reports`` row | failed with its reason; the run's row and verdict untouched) and
# published (``verdict["report_state"]``, ``verdict["report_error"]``), so every surface that
# links to the report waits for it or says why it is not there.

from __future__ import annotations

import asyncio
import contextlib
import logging
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol

from daemon.analysis import pipeline
from daemon.analysis.judge import Judgement
from daemon.machines.setup import MachineSetup
from daemon.reports.compensation import verification_of
from daemon.store import report_jobs
from daemon.store.journal import Store


class Session(Protocol):
    """What the job needs of ``daemon.run.session.Session`` (no import: it imports us)."""

    store: Store
    setup: MachineSetup
    reports_dir: Path
    baseline: Any
    verdict: dict[str, Any] | None
    run_id: str | None

    def _publish(self) -> None: ...


log = logging.getLogger("rumba.session")

WRITING, WRITTEN, FAILED = report_jobs.WRITING, report_jobs.WRITTEN, report_jobs.FAILED
STOPPED = "the daemon stopped while it was being written"


def start(session: Session, run_id: str, analysis: pipeline.RunAnalysis,
          judgement: Judgement) -> asyncio.Task:
    """Render the report of ``run_id`` (its run has ended) in a worker; the task never raises
    (a failure is journaled and published, the verdict stays)."""
    verdict = session.verdict if session.verdict is not None else {}
    verdict["report_state"] = WRITING
    report_jobs.begin(session.store, run_id)  # journaled before the run's end is published
    baseline = session.baseline  # the next run replaces the session's own
    return asyncio.get_running_loop().create_task(
        _write(session, run_id, verdict, analysis, judgement, baseline),
        name=f"report-{run_id}")


async def _write(session: Session, run_id: str, verdict: dict, analysis: pipeline.RunAnalysis,
                 judgement: Judgement, baseline: object) -> None:
    store, setup = session.store, session.setup
    try:
        # matplotlib's import is slow: in the worker too, never on the event loop
        report = await asyncio.to_thread(_report_module)
        run, trend = store.run(run_id), store.trend(setup.name)  # the journal: loop thread
        verified = verification_of(store, run, analysis.data, setup)  # before/after
        paths = await asyncio.to_thread(report.write_report, session.reports_dir, run,
                                        analysis.data, judgement, analysis.centre_rows, trend,
                                        setup.tolerances, report.audit_of(setup, baseline),
                                        verified)
        report_jobs.written(store, run_id, *paths)  # the PDF beside the HTML (pdf_path)
        verdict["report"] = str(paths[0])
        verdict["pdf"] = str(report.pdf_path(paths[0]))
        verdict["report_state"] = WRITTEN
        log.info("%s %s report written: %s", setup.name, run_id, paths[0])
    except asyncio.CancelledError:
        _failed(session, run_id, verdict, STOPPED)
        raise
    except Exception as e:  # the verdict stands; the report's absence is said, with why
        log.exception("%s %s: report not written", setup.name, run_id)
        _failed(session, run_id, verdict, f"{type(e).__name__}: {e}")
    if session.run_id == run_id:  # a later run's status is not this run's
        session._publish()  # the session's own status, told to its listeners


def _report_module() -> ModuleType:
    from daemon.reports import report  # matplotlib's import is slow: only when a run gets here

    return report


def _failed(session: Session, run_id: str, verdict: dict, why: str) -> None:
    """The verdict stands; the job's end and why, journaled and published (not the run's
    reason: the run ended DONE, its report is another matter)."""
    verdict["report_state"] = FAILED
    verdict["report_error"] = " ".join(why.split())[:report_jobs.REASON_CHARS]
    try:
        report_jobs.failed(session.store, run_id, why)
    except Exception as e:  # the journal gone: the log keeps it
        log.error("%s %s: could not journal the report failure: %s", session.setup.name,
                  run_id, e)


async def settle(task: asyncio.Task | None, wait_s: float) -> None:
    """The daemon stops: let a report being written finish for ``wait_s`` (rendering takes
    seconds), then cancel it — journaled failed, "the daemon stopped while it was being
    written" — so no job is left 'writing' and the journal is closed after it."""
    if task is None or task.done():
        return
    try:
        await asyncio.wait_for(asyncio.shield(task), wait_s)
    except TimeoutError:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
