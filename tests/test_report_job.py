"""The report off the run's critical path: the verdict is journaled, written
back and the run's end published before the report is rendered; the rendering's end is
journaled and published; a failure keeps the verdict and says why; ``wait`` waits for it."""

from __future__ import annotations

import asyncio
import threading

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
from daemon.analysis.replay_link import Faults, ReplayLink, prepare_from_rows
from daemon.reports import report
from daemon.run.session import Session
from daemon.store import report_jobs
from daemon.store.journal import Store


@pytest.fixture
def env(tmp_path):
    setup = thesis_setup()
    rows = thesis_rows(setup)
    store = Store(tmp_path / "j.sqlite")
    link = ReplayLink(rows, setup.machine, faults=Faults())
    s = Session(setup, link, store, tmp_path / "reports", prepare=prepare_from_rows(rows))
    yield s, link, store
    store.close()


async def test_the_run_ends_and_the_verdict_is_written_back_before_the_report(env, monkeypatch):
    s, link, store = env
    entered, go_on = threading.Event(), threading.Event()
    seen: list[dict] = []
    real = report.write_report

    def held(*a, **kw):
        entered.set()
        if not go_on.wait(60):
            raise TimeoutError("the test never let the report go on")
        return real(*a, **kw)

    monkeypatch.setattr(report, "write_report", held)
    s.listeners.append(lambda st: seen.append({**st, "verdict": dict(st["verdict"] or {})}))
    run_id = s.start("hmi")
    while not entered.is_set():  # the worker is rendering: where is the run?
        await asyncio.sleep(0.01)
        assert s._task is not None
        if s._task.done() and s._report_task is None:
            s._task.result()
            pytest.fail("the run ended without starting its report")
    run = store.run(run_id)
    assert run.state == "DONE" and store.verdict(run_id)["written_back"]
    assert [v.status for v in link.verdicts] == ["PASS"]
    assert store.report(run_id) is None
    job = report_jobs.get(store, run_id)  # journaled before the run's end was published
    assert job is not None and job.state == "writing" and job.ended_at is None
    st = s.status()
    assert st["state"] == "IDLE" and not st["busy"]
    assert st["verdict"]["report_state"] == "writing" and "report" not in st["verdict"]
    go_on.set()
    final = await s.wait()  # rumba verify: waits for the report, then prints its path
    job = report_jobs.get(store, run_id)
    assert job is not None and job.state == "written" and job.reason == ""
    html, js = store.report(run_id)
    assert html.is_file() and js.is_file() and report.pdf_path(html).is_file()
    assert final["verdict"]["report"] == str(html)
    assert final["verdict"]["report_state"] == "written"
    assert seen[-1]["verdict"]["report_state"] == "written"  # published to the listeners
    first_end = next(x for x in seen if x["state"] == "IDLE")
    assert first_end["verdict"]["report_state"] == "writing"  # published before the report


async def test_a_report_that_fails_keeps_the_verdict_and_says_why(env, monkeypatch):
    s, link, store = env

    def broken(*_a, **_kw):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(report, "write_report", broken)
    run_id = s.start("hmi")
    final = await s.wait()
    assert final["state"] == "IDLE" and final["verdict"]["status"] == "PASS"
    assert final["verdict"]["report_state"] == "failed"
    assert "No space left on device" in final["verdict"]["report_error"]
    assert final["reason"] == ""  # the run's reason is the run's: it ended DONE
    run = store.run(run_id)  # journaled: the run stays DONE with its verdict
    assert run.state == "DONE" and run.verdict == "PASS" and store.report(run_id) is None
    assert run.reason == ""
    job = report_jobs.get(store, run_id)  # the report job's own row says why
    assert job is not None and job.state == "failed" and job.ended_at is not None
    assert job.reason.startswith("OSError: [Errno 28] No space left on device"), job.reason
    assert [v.status for v in link.verdicts] == ["PASS"]


async def test_a_daemon_stopping_under_the_report_journals_it_failed_and_leaves_nothing(
        env, monkeypatch):
    """Service.stop → Session.shutdown: the report is given its bounded wait, then cancelled;
    the job ends failed naming the stop (never left 'writing'), the run DONE with its verdict
    written back, no task of the session left running."""
    s, link, store = env
    entered, go_on = threading.Event(), threading.Event()
    real = report.write_report

    def held(*a, **kw):
        entered.set()
        go_on.wait(60)  # released after the shutdown: the stop does not wait for it
        return real(*a, **kw)

    monkeypatch.setattr(report, "write_report", held)
    run_id = s.start("hmi")
    while not entered.is_set():
        await asyncio.sleep(0.01)
        assert not (s._task.done() and s._report_task is None), s.status()
    try:
        await s.shutdown("the daemon stopping", report_wait_s=0.05)
    finally:
        go_on.set()
    assert s._task.done() and s._report_task.done()
    job = report_jobs.get(store, run_id)
    assert job is not None and job.state == "failed"
    assert job.reason == "the daemon stopped while it was being written"
    assert s.status()["verdict"]["report_state"] == "failed"
    run = store.run(run_id)
    assert (run.state, run.verdict, run.reason) == ("DONE", "PASS", "")
    assert store.verdict(run_id)["written_back"] and store.report(run_id) is None
    assert [v.status for v in link.verdicts] == ["PASS"]


async def test_a_report_job_a_crash_left_writing_is_failed_at_the_next_start(tmp_path):
    store = Store(tmp_path / "j.sqlite")
    try:
        store.new_run("R1", "mill1", "cnc", state="DONE")
        report_jobs.begin(store, "R1")  # then kill -9
        assert report_jobs.mark_abandoned(store) == ["R1"]
        job = report_jobs.get(store, "R1")
        assert job is not None and (job.state, job.reason) == ("failed", report_jobs.ABANDONED)
        assert report_jobs.mark_abandoned(store) == []  # once
    finally:
        store.close()


async def test_sigterm_on_rumba_run_under_the_report_stops_the_daemon_cleanly(tmp_path,
                                                                           monkeypatch):
    """``rumba run``'s SIGTERM handler stops the service (``serve`` → ``Service.stop``) while
    a report is being written: the stop returns, the report job is journaled failed naming
    the stop before the journal closes, the verdict written back, no report task left; the
    next start finds nothing left 'writing'."""
    from benchmarks.rigs.daemon_helpers import write_daemon_yaml
    from daemon.config import load_daemon_config
    from daemon.run import session as session_mod
    from daemon.service.service import Service

    cfg = load_daemon_config(write_daemon_yaml(tmp_path))
    setup = thesis_setup()
    rows = thesis_rows(setup)
    links: list[ReplayLink] = []
    entered, go_on = threading.Event(), threading.Event()
    real = report.write_report

    def held(*a, **kw):
        entered.set()
        go_on.wait(60)
        return real(*a, **kw)

    def factory(s):
        links.append(ReplayLink(rows, s.machine))
        return links[-1]

    monkeypatch.setattr(report, "write_report", held)
    monkeypatch.setattr(session_mod, "REPORT_STOP_WAIT_S", 0.1)  # the worker is held anyway
    svc = Service(cfg, factory, prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        s = svc.sessions["mill1"]
        run_id = s.start("hmi")
        while not entered.is_set():
            await asyncio.sleep(0.01)
            assert not (s._task.done() and s._report_task is None), s.status()
    finally:
        try:
            await svc.stop()
        finally:
            go_on.set()
    assert not [t for t in asyncio.all_tasks() if t.get_name().startswith("report-")
                and not t.done()]
    assert [v.status for v in links[0].verdicts] == ["PASS"]
    store = Store(cfg.store_path)
    try:
        job = report_jobs.get(store, run_id)
        assert job is not None and job.state == "failed"
        assert job.reason == "the daemon stopped while it was being written"
        assert store.run(run_id).state == "DONE" and store.verdict(run_id)["written_back"]
        assert report_jobs.mark_abandoned(store) == []  # the next start: nothing left writing
    finally:
        store.close()
