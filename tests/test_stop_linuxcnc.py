"""Stops against a real LinuxCNC 2.9 (issue 20, item 6; rows of the stop matrix that need the
session's LinuxCNC, tests/conftest.py ``lcnc``): Ctrl-C on a real ``rumba verify`` process
mid-capture, and an abort pressed on the CNC side (``set abort`` from another linuxcncrsh
client) mid-capture. Each ends with the run journaled with its cause and phase, LinuxCNC idle and
standing still, and a next run taking its first hits (then stopped: a 1-pose plan, no whole run).
Run with ``pytest -m linuxcnc``."""

from __future__ import annotations

import asyncio
import shutil
import signal
import socket
import time
from pathlib import Path

import pytest
import yaml

from contracts.setup_files import plan_from_dict
from daemon.machines.setup import MachineSetup
from daemon.run.session import State
from tests.linuxcnc_helpers import ARTEFACT, MACHINE, Rsh, _link, _session, _setup
from tests.stop_helpers import latest_run
from tests.test_stop_signals import _rumba

pytestmark = [pytest.mark.linuxcnc,
              pytest.mark.skipif(shutil.which("linuxcnc", path="/usr/bin") is None,
                                 reason="LinuxCNC not installed (bash .ci/install-peers.sh "
                                        "linuxcnc)")]

ONE_POSE = {"name": "one", "stylus_diameter_mm": 6, "poses": [[30, 60]],
            "standoff_mm": 1, "overtravel_mm": 1, "clearance_mm": 5,
            "feeds": {"probe_mm_min": 300, "approach_mm_min": 3000}}
WAIT_S = 120.0  # a safety net; every wait ends on an event first


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


def _until_capturing(proc, db: Path, not_run: str | None = None) -> str:
    """Wait for a first journaled hit of a run other than ``not_run``; return its id."""
    deadline = time.monotonic() + WAIT_S
    while True:
        row = latest_run(db)
        if row and row[0] != not_run and row[3] >= 1:
            return row[0]
        if proc.poll() is not None:
            raise AssertionError(f"verify ended ({proc.returncode}) before capturing: "
                                 f"{proc.stderr.read()}")
        assert time.monotonic() < deadline, "no hit journaled"
        time.sleep(0.05)


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
    proc = _rumba(*argv)
    run1 = _until_capturing(proc, db)
    _interrupt(proc)
    rid, state, reason, _ = latest_run(db)  # type: ignore[misc]
    assert (rid, state) == (run1, "ABORTED"), reason
    assert reason.startswith("aborted by Ctrl-C (SIGINT) during CAPTURE"), reason
    _idle_and_still(port)
    # The next run, without restarting anything: LinuxCNC takes its program (first hits).
    again = _rumba(*argv)
    run2 = _until_capturing(again, db, not_run=run1)
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
        # refused, named with its line (an involuntary stop: FAILED, the phase named).
        assert row.state == "FAILED" and row.reason.endswith("(during CAPTURE)"), row.reason
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
