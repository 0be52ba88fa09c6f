"""Every stop leaves a defined state: phase × trigger × transport against the
simulated CNC behind its real front-end (asyncua server, pymodbus server, a pty), one simulator
per transport for the whole module (a stop that left one out of step fails every later row).
Each row holds a run in its phase, stops it, and checks: the journal row ABORTED (a person, a
RESET the link reports) or INTERRUPTED (the daemon stopping, a lost link, a controller gone
silent) naming the phase and the cause, the controller no longer running the program, and the
next run on the same session, link and simulator taking a new program (its first hit
journaled). The report is no phase: it is written after the run's end (daemon/run/report_job.py),
so its rows stop the run's report job instead — a person's abort (HMI, CAN panel, Ctrl-C on
``rumba verify``) finds no run to abort and the report is finished; the daemon stopping
(SIGTERM on ``rumba run``: ``Session.shutdown``) gives it its bounded wait, then journals it
failed with the reason; either way the verdict stays journaled and written back, nothing is
left running or 'writing'. The module ends with a complete run per transport on the same
simulators."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading

import pytest
import pytest_asyncio

from benchmarks.rigs.rig_helpers import make_truth, start_rig
from contracts.jobs import VERDICT_CODES
from daemon.config import load_daemon_config
from daemon.run.session import Session, State
from daemon.service.service import make_link
from daemon.store import report_jobs
from daemon.store.journal import Store
from simulators.controller import VirtualController
from tests.stop_helpers import REPORT_JOB, Hold, held_session, until_reached, write_config

TRANSPORTS = ("opcua", "modbus", "serial-pty", "sinumerik", "lsv2", "haas")
DIALECT = {"sinumerik": "siemens", "lsv2": "heidenhain", "haas": "haas"}  # their own only
PHASES = ("PREPARE", "CAPTURE", "IDENTIFY", "WRITE-BACK")
OPERATOR = ("hmi", "CAN panel")  # session.abort(source): a person
DAEMON = "the daemon stopping"  # session.interrupt(cause), as Service.stop (SIGTERM on rumba run)
SIGINT = "Ctrl-C (SIGINT)"  # rumba verify's signal handler: session.abort(source)
ROWS = ([(t, p, c) for t in TRANSPORTS for p in PHASES for c in (*OPERATOR, DAEMON)]
        + [(t, "CAPTURE", c) for t in TRANSPORTS for c in ("cnc", "link loss")]
        + [(t, REPORT_JOB, c) for t in TRANSPORTS for c in (*OPERATOR, SIGINT, DAEMON)])
SHORT = {"CAN panel": "CAN", DAEMON: "daemon-stop", "link loss": "link-loss", SIGINT: "SIGINT",
         REPORT_JOB: "report-job"}
PARAMS = [pytest.param(t, p, c, id=f"{t}-{SHORT.get(p, p)}-{SHORT.get(c, c)}")
          for t, p, c in ROWS]


class _Tracebacks(logging.Handler):
    """Every log record that carries a traceback (the loop's exception handler logs one for a
    failed callback)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info or "Traceback" in record.getMessage():
            self.records.append(record)


@pytest.fixture(autouse=True)
def no_traceback_logged():
    """The stops leave the log free of tracebacks: none logged by the daemon's code, its
    libraries or the event loop, in the row or after it."""
    handler = _Tracebacks()
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield
    finally:
        root.removeHandler(handler)
    assert not handler.records, [f"{r.name}: {r.getMessage()[:300]}" for r in handler.records]


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def rigs():
    made: dict = {}

    async def get(transport: str):
        if transport not in made:
            made[transport] = await start_rig(transport, VirtualController(make_truth()))
        return made[transport]

    yield get
    for rig in made.values():
        with contextlib.suppress(Exception):
            await rig.close()


def _link(rig, trigger: str) -> dict:
    link = dict(rig.link)
    if rig.transport.startswith("serial") and trigger == "cnc":
        link["result_timeout_s"] = 2  # DNC never hears of a RESET: the silence is the sign
    return link


async def _open(rig, tmp_path, monkeypatch, hold: Hold, trigger: str = ""):
    cfg = load_daemon_config(write_config(tmp_path, _link(rig, trigger),
                                          dialect=DIALECT.get(rig.transport, "fanuc")))
    setup = cfg.machines["mill1"]
    store = Store(cfg.store_path)
    link = make_link(setup)
    await link.connect()
    return held_session(setup, link, store, cfg.reports_dir, hold, monkeypatch), store, link


async def _stop(session, rig, link, trigger: str, hold: Hold) -> None:
    if trigger == "cnc":
        await rig.ctrl.abort()  # RESET pressed on the control
        hold.go_on.set()
    elif trigger == "link loss":
        await link.close()  # the connection drops under the run
        hold.go_on.set()
    elif trigger == DAEMON:
        assert await session.interrupt(trigger)
    else:
        assert await session.abort(trigger)
    async with asyncio.timeout(60):
        await session.wait()


async def _dnc_program_ended(rig, verdict_sent: bool) -> None:
    """Plain DNC has no remote reset: the tape was closed at a block's end, the control ends
    the program after the blocks it holds (an event, not a guess), then reads the ERROR verdict
    tape the run's end sent (not after a RESET: the tape was open)."""
    async with asyncio.timeout(30):
        while rig.ctrl.state in ("running", "hold") or (verdict_sent and rig.ctrl.verdict == 0):
            await rig.ctrl.wait_done()
            await asyncio.sleep(0.05)


def _diagnose(rig) -> str:
    """Where the simulated control stands (a run that never started names it)."""
    fe = rig.extra.get("frontend")
    if fe is not None and hasattr(fe, "diagnose"):
        return f"control {rig.ctrl.state}, resets {rig.ctrl.resets}; {fe.diagnose()}"
    tape = "" if fe is None else (
        f"; tape: in program {fe._in_program}, blocks {fe._tape_blocks}, discard "
        f"{fe._discard}, xoff {fe._xoff}, buffer {bytes(fe._buf[:60])!r}, alarms {fe.alarms}")
    return f"control {rig.ctrl.state}, resets {getattr(rig.ctrl, 'resets', '?')}{tape}"


async def _stop_report_job(session, rig, store, run_id: str, trigger: str, hold: Hold) -> None:
    """Stop the run's report job while the worker writes it, then check what is left: the run
    DONE with its verdict journaled and written back (the controller read it), the job ended —
    finished after a person's abort (there is no run to abort), failed naming the stop when
    the daemon stops — and nothing running or 'writing'."""
    assert session.state == State.IDLE and not session.busy  # the run ended before its report
    if trigger == DAEMON:
        try:  # the wait is short here: the held worker never finishes before its release
            await session.shutdown(trigger, report_wait_s=0.1)
        finally:
            hold.release()
    else:
        try:
            assert not await session.abort(trigger)  # nothing runs: the HMI answers 409
        finally:
            hold.release()
        async with asyncio.timeout(60):
            await session.wait()
    row, verdict = store.run(run_id), store.verdict(run_id)
    assert (row.state, row.reason) == ("DONE", ""), row.reason
    assert verdict is not None and verdict["written_back"] and row.verdict == verdict["status"]
    if rig.transport.startswith("serial"):
        await _dnc_program_ended(rig, verdict_sent=True)
    assert rig.ctrl.verdict == VERDICT_CODES[verdict["status"]] != VERDICT_CODES["ERROR"], \
        (rig.ctrl.verdict, verdict["status"])
    job = report_jobs.get(store, run_id)
    assert session._report_task is not None and session._report_task.done()
    st = session.status()
    assert st["state"] == "IDLE" and not st["busy"]
    if trigger == DAEMON:
        assert job is not None and job.state == "failed", job
        assert job.reason == "the daemon stopped while it was being written"
        assert store.report(run_id) is None
        assert st["verdict"]["report_state"] == "failed"
    else:
        assert job is not None and (job.state, job.reason) == ("written", ""), job
        html, _ = store.report(run_id)
        assert html.is_file() and st["verdict"]["report"] == str(html)


def _expected(transport: str, phase: str, trigger: str) -> tuple[str, str]:
    if trigger in OPERATOR:
        return "ABORTED", f"aborted by {trigger} during {phase}"
    if trigger == DAEMON:
        return "INTERRUPTED", f"interrupted by {trigger} during {phase}"
    if trigger == "cnc" and not transport.startswith("serial"):
        return "ABORTED", "aborted on the controller during CAPTURE"
    # plain DNC never hears of a RESET: the results stop coming (INTERRUPTED, as a lost link)
    return "INTERRUPTED", "(during CAPTURE)"


@pytest.mark.asyncio(loop_scope="module")
@pytest.mark.parametrize(("transport", "phase", "trigger"), PARAMS)
async def test_every_stop_leaves_a_defined_state_and_the_next_run_starts(
        rigs, tmp_path, monkeypatch, transport, phase, trigger):
    rig = await rigs(transport)
    rig.ctrl.reseed(0)
    rig.ctrl.verdict = 0  # as the start-of-shift macro clears it
    hold = Hold(phase)
    session, store, link = await _open(rig, tmp_path, monkeypatch, hold, trigger)
    try:
        run1 = session.start("hmi")
        await until_reached(session, hold, diagnose=lambda: _diagnose(rig))
        if phase == REPORT_JOB:
            await _stop_report_job(session, rig, store, run1, trigger, hold)
        else:
            await _stop(session, rig, link, trigger, hold)
            hold.release()
            state, why = _expected(transport, phase, trigger)
            row = store.run(run1)
            assert (row.state, session.state) == (state, State(state)), row.reason
            assert row.reason.startswith(why) or why in row.reason, row.reason
            if transport.startswith("serial"):
                await _dnc_program_ended(rig, verdict_sent=trigger in (*OPERATOR, DAEMON))
        if trigger != "link loss":  # the reset reached the control: nothing runs there
            assert rig.ctrl.state not in ("running", "hold"), rig.ctrl.state
        # The next run: the controller takes its program (a first hit), then it is stopped
        # there (a whole run per transport is the last test).
        hold.phase, hold._release = "CAPTURE", threading.Event()
        hold.reached, hold.go_on = asyncio.Event(), asyncio.Event()
        run2 = session.start("hmi")
        await until_reached(session, hold, diagnose=lambda: _diagnose(rig))
        assert store.hit_count(run2) >= 1
        rig.ctrl.verdict = 0
        assert await session.abort("hmi")
        assert store.run(run2).state == "ABORTED"
        if transport.startswith("serial"):
            # The next row's link is a new one (a new rumba verify): plain DNC result lines
            # carry no run id, so a program the control still finishes would print into that
            # run (a link drops such lines only after its own stop). Wait for the end here.
            await _dnc_program_ended(rig, verdict_sent=True)
    finally:
        hold.release()
        with contextlib.suppress(Exception):
            await link.close()
        store.close()


@pytest.mark.asyncio(loop_scope="module")
@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_a_complete_run_after_the_matrix(rigs, tmp_path, monkeypatch, transport):
    """After every stop above, the same simulator runs a whole verification to its verdict."""
    rig = await rigs(transport)
    rig.ctrl.reseed(0)
    session, store, link = await _open(rig, tmp_path, monkeypatch, Hold(None))
    try:
        run_id = session.start("hmi")
        async with asyncio.timeout(120):
            st = await session.wait()
        assert st["state"] == "IDLE", st["reason"]
        assert store.run(run_id).state == "DONE" and st["verdict"]["status"]
    finally:
        await link.close()
        store.close()


MAP_STOPS = [pytest.param(t, c, id=f"{t}-map-prompt-{SHORT.get(c, c)}")
             for t in TRANSPORTS for c in (*OPERATOR, DAEMON)]


@pytest.mark.asyncio(loop_scope="module")
@pytest.mark.parametrize(("transport", "trigger"), MAP_STOPS)
async def test_a_stop_at_the_map_prompt_keeps_the_first_placement(rigs, tmp_path, transport,
                                                                   trigger):
    """A map job (daemon/run/map_job.py) waiting for its operator between placements, the
    machine idle: a stop ends it ABORTED / INTERRUPTED naming the prompt, the first placement's
    hits kept, nothing running on the control, and the next run runs to its verdict."""
    import yaml

    rig = await rigs(transport)
    rig.ctrl.reseed(0)
    rig.ctrl.verdict = 0
    path = write_config(tmp_path, _link(rig, trigger), dialect=DIALECT.get(transport, "fanuc"))
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    machine = doc["machines"][0]
    job = {"name": "stop-map", "placements": [
        {"name": n, "plan": machine["plan"], "artefact": machine["artefact"]}
        for n in ("P1", "P2")]}
    (tmp_path / "map-job.yaml").write_text(yaml.safe_dump(job), encoding="utf-8")
    machine["map_job"] = str(tmp_path / "map-job.yaml")
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    cfg = load_daemon_config(path)
    store = Store(cfg.store_path)
    link = make_link(cfg.machines["mill1"])
    await link.connect()
    session = Session(cfg.machines["mill1"], link, store, cfg.reports_dir)
    try:
        run1 = session.start("hmi", job="map")
        async with asyncio.timeout(120):
            while session.prompt is None:
                assert session.busy, f"{session.state}: {session.reason} ({_diagnose(rig)})"
                await asyncio.sleep(0.02)
        if trigger == DAEMON:
            assert await session.interrupt(trigger)
        else:
            assert await session.abort(trigger)
        end = "INTERRUPTED" if trigger == DAEMON else "ABORTED"
        row = store.run(run1)
        assert (row.state, session.state) == (end, State(end)), row.reason
        assert "waiting for the operator to move the artefact to P2" in row.reason
        assert row.hits == 4 * 4 * 5 and session.prompt is None  # placement 1 kept
        await _error_read(rig)
        # the next run takes a new program and runs to its verdict (stopping it while its link
        # polls is the matrix's CAPTURE rows' job, with the link held)
        run2 = session.start("hmi")
        async with asyncio.timeout(120):
            st = await session.wait()
        assert st["state"] == "IDLE" and store.run(run2).state == "DONE", st["reason"]
        await _error_read(rig)
    finally:
        with contextlib.suppress(Exception):
            await link.close()
        store.close()


async def _error_read(rig) -> None:
    """Nothing runs on the control any more after the stop (plain DNC: the tape's blocks
    played out and the ERROR verdict read)."""
    if rig.transport.startswith("serial"):
        await _dnc_program_ended(rig, verdict_sent=True)
    async with asyncio.timeout(30):
        while rig.ctrl.state in ("running", "hold"):
            await asyncio.sleep(0.02)
