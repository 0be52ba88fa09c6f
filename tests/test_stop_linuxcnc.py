"""Stops against a real LinuxCNC 2.9 (the stop matrix on the session's
LinuxCNC, tests/conftest.py ``lcnc``), phase × trigger: PREPARE, CAPTURE and IDENTIFY × an
operator's abort (the HMI's ``session.abort``), SIGINT / SIGTERM on ``rumba verify`` (a real
process mid-capture; in this process, a real signal to ``verify()`` held in its phase), the
daemon stopping (``session.interrupt``), an abort on the CNC side (``set abort`` from another
linuxcncrsh client) and a lost link (the TCP connection to linuxcncrsh reset and refused, then
back). Each row ends with the run journaled ABORTED or INTERRUPTED with its cause and phase,
LinuxCNC idle and standing still (ERROR written back where the link was up), and the next run
(the same session; a new ``verify``) taking its first hits, then stopped: a 1-pose plan, no
whole run. Run with ``pytest -m linuxcnc``."""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import socket
import time
from pathlib import Path

import pytest
import yaml

from contracts.setup_files import plan_from_dict
from daemon.analysis import pipeline
from daemon.cli.commands.verify import verify
from daemon.config import load_daemon_config
from daemon.machines.setup import MachineSetup
from daemon.run.session import State
from daemon.store.journal import Store
from drivers.registry import make_link
from tests.linuxcnc_helpers import ARTEFACT, MACHINE, Rsh, _link, _session, _setup, halcmd
from tests.stop_helpers import (
    Hold,
    TcpCut,
    held_session,
    latest_run,
    rumba_process,
    until_capturing,
    until_reached,
)

pytestmark = [pytest.mark.linuxcnc,
              pytest.mark.skipif(shutil.which("linuxcnc", path="/usr/bin") is None,
                                 reason="LinuxCNC not installed (bash .ci/install-peers.sh "
                                        "linuxcnc)")]

ONE_POSE = {"name": "one", "stylus_diameter_mm": 6, "poses": [[30, 60]],
            "standoff_mm": 1, "overtravel_mm": 1, "clearance_mm": 5,
            "feeds": {"probe_mm_min": 300, "approach_mm_min": 3000}}
WAIT_S = 120.0  # a safety net; every wait ends on an event first
ERROR_CODE = 4  # contracts.jobs VERDICT_CODES["ERROR"] on motion.analog-out-00


def _config(tmp: Path, link: dict) -> Path:
    plan = tmp / "plan.yaml"
    plan.write_text(yaml.safe_dump(ONE_POSE), encoding="utf-8")
    doc = {"store": {"path": str(tmp / "journal.sqlite")}, "reports_dir": str(tmp / "reports"),
           "hmi": {"enabled": False},
           "machines": [{"name": "lcnc", "machine": str(MACHINE), "artefact": str(ARTEFACT),
                         "plan": str(plan), "dialect": "linuxcnc", "link": link,
                         "touch_timeout_s": 60}]}
    path = tmp / "daemon.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    return path


def _idle_and_still(port: int) -> None:
    rsh = Rsh(port)
    try:
        first = rsh.floats("get joint_pos")
        time.sleep(0.5)
        assert rsh.floats("get joint_pos") == first  # the machine stands still
        assert rsh.ask("get program_status") == "PROGRAM_STATUS IDLE"
    finally:
        rsh.close()


def _interrupt(proc) -> str:
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "ProgrammingError" not in err, err
    return err


def test_sigint_on_rumba_verify_against_linuxcnc_mid_capture(lcnc, tmp_path: Path) -> None:
    port = lcnc.peer.port
    cfg = _config(tmp_path, _link(lcnc.peer, "remote"))
    db = tmp_path / "journal.sqlite"
    argv = ("verify", "--config", str(cfg), "--machine", "lcnc", "--quiet")
    proc = rumba_process(*argv)
    run1 = until_capturing(proc, db)
    _interrupt(proc)
    rid, state, reason, _ = latest_run(db)  # type: ignore[misc]
    assert (rid, state) == (run1, "ABORTED"), reason
    assert reason.startswith("aborted by Ctrl-C (SIGINT) during CAPTURE"), reason
    _idle_and_still(port)
    # The next run, without restarting anything: LinuxCNC takes its program (first hits).
    again = rumba_process(*argv)
    run2 = until_capturing(again, db, not_run=run1)
    _interrupt(again)
    assert latest_run(db)[:2] == (run2, "ABORTED")  # type: ignore[index]
    _idle_and_still(port)


async def test_abort_on_the_linuxcnc_side_mid_capture(lcnc, tmp_path: Path) -> None:
    port = lcnc.peer.port
    setup = _setup(_link(lcnc.peer, "remote"))
    setup = MachineSetup(**{**setup.__dict__, "plan": plan_from_dict(ONE_POSE)})
    session, store = await _session(setup, tmp_path)
    try:
        run1 = session.start("cli")
        async with asyncio.timeout(WAIT_S):
            while store.hit_count(run1) < 1:
                assert session.state not in (State.FAILED, State.ABORTED), session.reason
                await asyncio.sleep(0.05)

        def press_abort() -> None:
            """Another linuxcncrsh client (the operator's abort): hello, enable, abort, with
            linuxcncrsh's default wait (the command received, not done: a run is in motion)."""
            rsh = Rsh.__new__(Rsh)
            rsh.sock, rsh.buf = socket.create_connection(("127.0.0.1", port), timeout=60), b""
            try:
                assert rsh.ask("hello EMC operator 1.0").startswith("HELLO ACK")
                rsh.sock.sendall(b"set echo off\r\nset verbose on\r\nset enable EMCTOO\r\n"
                                 b"set abort\r\n")
                replies = [rsh.line() for _ in range(4)]
                while replies[-1] != "SET ABORT ACK":
                    assert "NAK" not in replies[-1], replies
                    replies.append(rsh.line())
            finally:
                rsh.close()

        await asyncio.to_thread(press_abort)
        async with asyncio.timeout(WAIT_S):
            await session.wait()
        row = store.run(run1)
        # The operator's client took linuxcncrsh's enable to abort: the run's next block is
        # refused (named with its line), and the link tells why: ABORTED on the controller.
        assert row.state == "ABORTED", row.reason
        assert row.reason.startswith("aborted on the controller during CAPTURE: another "
                                     "linuxcncrsh client took the control"), row.reason
        assert "block refused (SET MDI NAK)" in row.reason, row.reason
        await asyncio.to_thread(_idle_and_still, port)
        # The next run on the same session and link takes its first hits, then is stopped.
        run2 = session.start("cli")
        async with asyncio.timeout(WAIT_S):
            while store.hit_count(run2) < 1:
                assert session.state not in (State.FAILED, State.ABORTED), session.reason
                await asyncio.sleep(0.05)
        assert await session.abort("hmi")
        assert store.run(run2).state == "ABORTED"
        await asyncio.to_thread(_idle_and_still, port)
    finally:
        await session.link.close()
        store.close()


# ------------------------------------------------------------------------ phase × trigger
SIGNALS = {"SIGINT": (signal.SIGINT, "Ctrl-C (SIGINT)"), "SIGTERM": (signal.SIGTERM, "SIGTERM")}
GRID = [("PREPARE", "hmi"), ("PREPARE", "SIGINT"), ("PREPARE", "link loss"),
        ("CAPTURE", "hmi"), ("CAPTURE", "SIGTERM"), ("CAPTURE", "daemon stop"),
        ("CAPTURE", "link loss"),
        ("IDENTIFY", "hmi"), ("IDENTIFY", "SIGTERM")]
"""With the two rows above (SIGINT on a ``rumba verify`` process and the CNC-side abort, both
mid-capture). A CNC-side abort outside CAPTURE stops nothing of the run's (the controller is
idle then); a lost link in IDENTIFY is noticed at WRITE-BACK, the row in PREPARE at STREAM."""


def _expected(phase: str, trigger: str) -> tuple[str, str]:
    if trigger == "hmi":
        return "ABORTED", f"aborted by hmi during {phase}"
    if trigger in SIGNALS:
        return "ABORTED", f"aborted by {SIGNALS[trigger][1]} during {phase}"
    if trigger == "daemon stop":
        return "INTERRUPTED", f"interrupted by the daemon stopping during {phase}"
    return "INTERRUPTED", "linuxcncrsh"  # connection lost / closed, in the phase that used it


def _clear_verdict(port: int) -> None:
    """No verdict on the control (as the start-of-shift macro clears it): M68 E0 Q0."""
    rsh = Rsh(port)
    try:
        rsh.home_mdi()
        rsh.mdi("M68 E0 Q0")  # set_wait done: answered once the block is done
    finally:
        rsh.close()


def _wait_still(port: int) -> None:
    """LinuxCNC idle and standing still: a lost link leaves it the block in hand to finish."""
    deadline = time.monotonic() + WAIT_S
    while True:
        try:
            _idle_and_still(port)
            return
        except AssertionError:
            assert time.monotonic() < deadline, "LinuxCNC still moving"


async def _verify_signalled(cfg: Path, hold: Hold, sig: signal.Signals) -> int:
    """``verify()`` as ``rumba verify`` runs it, held in ``hold.phase``, then a real signal to
    this process (its handler is the one verify installed on the event loop)."""
    def factory(setup: MachineSetup):
        link = make_link(setup.link)
        link.run = hold.capture(link.run)
        return link

    task = asyncio.ensure_future(verify(
        str(cfg), "lcnc", quiet=True, link_factory=factory,
        prepare=hold.in_thread("PREPARE", pipeline.prepare),
        analyse=hold.in_thread("IDENTIFY", pipeline.analyse)))
    reached = asyncio.ensure_future(hold.reached.wait())
    async with asyncio.timeout(WAIT_S):
        await asyncio.wait({task, reached}, return_when=asyncio.FIRST_COMPLETED)
    assert reached.done(), f"verify ended before {hold.phase}: {task.result()}"
    os.kill(os.getpid(), sig)
    async with asyncio.timeout(WAIT_S):
        code = await task
    hold.release()
    return code


async def _next_run_takes_hits(session, store: Store) -> None:
    """The next run on ``session`` takes its first hit from LinuxCNC, then is stopped."""
    run2 = session.start("hmi")
    async with asyncio.timeout(WAIT_S):
        while store.hit_count(run2) < 1:
            assert session.state not in (State.FAILED, State.ABORTED, State.INTERRUPTED), \
                session.reason
            await asyncio.sleep(0.05)
    assert await session.abort("hmi")
    assert store.run(run2).state == "ABORTED"


@pytest.mark.parametrize(("phase", "trigger"),
                         [pytest.param(p, t, id=f"{p}-{t.replace(' ', '-')}") for p, t in GRID])
async def test_stop_in_each_phase_on_linuxcnc(lcnc, tmp_path, monkeypatch, phase, trigger):
    port = lcnc.peer.port
    cut = TcpCut(port) if trigger == "link loss" else None
    link_port = await cut.start() if cut else port
    cfg_path = _config(tmp_path, {"transport": "linuxcnc", "port": link_port,
                                  "prelude_mdi": ["M429"]})
    await asyncio.to_thread(_clear_verdict, port)
    assert float(halcmd(lcnc.peer, "getp", "motion.analog-out-00")) == 0
    hold = Hold(phase)
    db = tmp_path / "journal.sqlite"
    if trigger in SIGNALS:
        sig, _ = SIGNALS[trigger]
        assert await _verify_signalled(cfg_path, hold, sig) == 128 + int(sig)
        session = None
    else:
        setup = load_daemon_config(cfg_path).machines["lcnc"]
        link = make_link(setup.link)
        await link.connect()
        session = held_session(setup, link, Store(db), tmp_path / "reports", hold, monkeypatch)
        session.start("hmi")
        await until_reached(session, hold, WAIT_S)
        if cut is not None:
            await cut.cut()  # the cable pulled: the run and the stop's abort find no LinuxCNC
            hold.release()
            async with asyncio.timeout(WAIT_S):
                await session.wait()
        elif trigger == "daemon stop":
            assert await session.interrupt("the daemon stopping")
        else:
            assert await session.abort("hmi")
        hold.release()
    try:
        _rid, state, reason, _ = latest_run(db)  # type: ignore[misc]
        want_state, want = _expected(phase, trigger)
        assert state == want_state and want in reason, reason
        if cut is None:
            assert reason.startswith(want), reason
            await asyncio.to_thread(_idle_and_still, port)
            assert float(halcmd(lcnc.peer, "getp", "motion.analog-out-00")) == ERROR_CODE
        else:  # the stop could not reach LinuxCNC: said so, and the next run stops it first
            assert f"(during {'STREAM' if phase == 'PREPARE' else phase})" in reason, reason
            assert "controller abort failed" in reason, reason
            await asyncio.to_thread(_wait_still, port)
            await cut.restore()
        if session is None:  # a new rumba verify: a new session and link
            setup = load_daemon_config(cfg_path).machines["lcnc"]
            session, _ = await _session(setup, tmp_path)  # the same journal
        await _next_run_takes_hits(session, session.store)
    finally:
        if session is not None:
            await session.link.close()
            session.store.close()
        if cut is not None:
            await cut.cut()
