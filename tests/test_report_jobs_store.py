"""A run's report job has its own record (migration 10, daemon/store/report_jobs.py): a journal
written before it opens with its reports as written jobs and its "report not written" reasons
as failed ones; the HMI's run list and the fleet store read the job, never the run's reason."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import psycopg
import pytest

from daemon.hmi.app import _run_dict
from daemon.store import report_jobs
from daemon.store.drain import Drainer
from daemon.store.journal import Store
from daemon.store.pg import PgStore
from daemon.store.schema import MIGRATIONS, SCHEMA_VERSION
from tests.fleet_helpers import fresh_db, start_postgres

OLD_REASON = "verdict written back; report not written: OSError: [Errno 28] No space left"


def _journal_v9(path: Path) -> None:
    """A journal as rumba left it before migration 10: a run with its report, a run whose
    report failed (the cause in the run's reason), a DONE run with neither, a failed run."""
    db = sqlite3.connect(path)
    with db:
        db.execute("CREATE TABLE schema_version (version INTEGER PRIMARY KEY, "
                   "applied_at REAL NOT NULL)")
        for version, step in enumerate(MIGRATIONS[:9], start=1):
            for stmt in step:
                db.execute(stmt)
            db.execute("INSERT INTO schema_version VALUES (?, 0)", (version,))
        for rid, state, reason in (("R-written", "DONE", ""), ("R-failed", "DONE", OLD_REASON),
                                   ("R-none", "DONE", ""),
                                   ("R-stopped", "FAILED", "probe did not trigger")):
            db.execute("INSERT INTO runs (id, machine, trigger, state, reason, started_at,"
                       " ended_at) VALUES (?, 'mill1', 'cnc', ?, ?, 100, 160)",
                       (rid, state, reason))
        db.execute("INSERT INTO reports VALUES ('R-written', '/r/R-written.html', "
                   "'/r/R-written.json')")
    db.close()


def test_an_old_journal_opens_with_its_report_jobs(tmp_path: Path) -> None:
    path = tmp_path / "j.sqlite"
    _journal_v9(path)
    store = Store(path)
    try:
        assert store.schema_version() == SCHEMA_VERSION >= 10
        done = report_jobs.get(store, "R-written")
        assert done is not None and (done.state, done.reason, done.ended_at) == \
            ("written", "", 160)
        failed = report_jobs.get(store, "R-failed")
        assert failed is not None and failed.state == "failed"
        assert failed.reason == "OSError: [Errno 28] No space left"  # the cause, no prefix
        assert report_jobs.get(store, "R-none") is None  # nothing to tell of
        assert report_jobs.get(store, "R-stopped") is None  # no verdict, no report job
        assert store.run("R-failed").reason == OLD_REASON  # nothing of the old row lost
        # the HMI's run list reads the job
        row = _run_dict(store.run("R-failed"), store)
        assert (row["report_state"], row["report_error"], row["report"]) == \
            ("failed", "OSError: [Errno 28] No space left", None)
        row = _run_dict(store.run("R-written"), store)
        assert (row["report_state"], row["report_error"]) == ("written", "")
        assert row["report"] == "/reports/R-written.html"
        assert _run_dict(store.run("R-none"), store)["report_state"] is None
    finally:
        store.close()
    again = Store(path)  # opened again: migrated once, nothing added twice
    try:
        assert again.db.execute("SELECT COUNT(*) FROM report_jobs").fetchone()[0] == 2
    finally:
        again.close()


def test_a_job_is_written_or_failed_once_ended(tmp_path: Path) -> None:
    store = Store(tmp_path / "j.sqlite")
    try:
        store.new_run("R1", "mill1", "cnc", state="DONE")
        report_jobs.begin(store, "R1")
        job = report_jobs.get(store, "R1")
        assert job is not None and not job.ended and job.ended_at is None
        report_jobs.failed(store, "R1", "ValueError: bad\n  line two " + "x" * 400)
        job = report_jobs.get(store, "R1")
        assert job is not None and job.ended and job.state == "failed"
        assert "\n" not in job.reason and len(job.reason) == report_jobs.REASON_CHARS
        assert job.reason.startswith("ValueError: bad line two x")
        report_jobs.begin(store, "R1")  # written again later: the new job replaces it
        report_jobs.written(store, "R1", tmp_path / "R1.html", tmp_path / "R1.json")
        job = report_jobs.get(store, "R1")
        assert job is not None and (job.state, job.reason) == ("written", "")
        assert store.report("R1") == (tmp_path / "R1.html", tmp_path / "R1.json")
        assert store.run("R1").reason == ""
    finally:
        store.close()


@pytest.fixture(scope="module")
def pg():
    server = start_postgres()
    yield server
    server.close()


@pytest.mark.peer
async def test_report_jobs_reach_the_fleet_store_and_its_run_list(pg, tmp_path: Path) -> None:
    dsn = fresh_db(pg)
    store = Store(tmp_path / "j.sqlite")
    drainer = Drainer(store, dsn)
    try:
        store.new_run("R1", "mill1", "cnc", state="WRITE-BACK")
        report_jobs.begin(store, "R1")
        store.set_state("R1", "DONE")
        await drainer.drain()
        fleet = await PgStore.connect(dsn, migrate=False)
        try:
            (run,) = await fleet.runs("mill1", 5)
            assert (run["state"], run["report_state"], run["has_report"]) == \
                ("DONE", "writing", False)
            report_jobs.failed(store, "R1", "OSError: disk full")
            await drainer.drain()
            (run,) = await fleet.runs("mill1", 5)
            assert (run["report_state"], run["report_error"], run["reason"]) == \
                ("failed", "OSError: disk full", "")
            assert await fleet.report_job("R1") == ("failed", "OSError: disk full")
        finally:
            await fleet.close()
        with psycopg.connect(dsn) as c:  # copied once, upserted on the run id
            assert c.execute("SELECT COUNT(*) FROM report_jobs").fetchone()[0] == 1
    finally:
        await drainer.stop()
        store.close()


def test_rumba_history_lists_a_failed_report_jobs_reason(tmp_path: Path, capsys) -> None:
    from benchmarks.rigs.daemon_helpers import write_daemon_yaml
    from daemon.config import load_daemon_config
    from tests.cli_helpers import run_cli

    cfg = write_daemon_yaml(tmp_path)
    store = Store(load_daemon_config(cfg).store_path)
    try:
        store.new_run("R1", "mill1", "cnc", state="WRITE-BACK")
        store.save_verdict("R1", "PASS", [], [], "PASS: all within limits")
        report_jobs.begin(store, "R1")
        store.set_state("R1", "DONE")
        report_jobs.failed(store, "R1", "OSError: disk full")
    finally:
        store.close()
    code, out, err = run_cli(["history", "--config", str(cfg)], capsys)
    assert code == 0, err
    line = next(ln for ln in out.splitlines() if "R1" in ln)
    assert "PASS: all within limits; report not written: OSError: disk full" in line, out
