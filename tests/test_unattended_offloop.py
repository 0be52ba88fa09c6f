"""The unattended compensation's write (halcmd, the HAL file replace) runs off the event loop,
bounded by a time budget, and a stop that lands in the middle of it waits for the
transaction to end — journal, pins and HAL file agree — and starts no verification run.
The LinuxCNC on this PC is faked at halcmd's level (tests/test_compensate_transaction.py);
the write is held in the middle by the test, from the event loop itself: a write on the loop
could never be released by it."""

from __future__ import annotations

import asyncio
import json
import threading
from pathlib import Path

import pytest

from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.compensation import journal as cj
from daemon.compensation.propose import journal_analyse
from daemon.config import load_daemon_config
from daemon.run.session import Refused, Session
from daemon.run.unattended import after_run
from daemon.store.journal import Store
from drivers.linuxcnc import halkins
from tests.test_compensate import LINKS, _world
from tests.test_compensate_transaction import X, _rows, fake_linuxcnc

GUARDS = {"max_change_um": 150, "max_change_urad": 100, "max_total_um": 200,
          "unattended": True}
HELD_S = 30.0  # how long a held setp waits for the test before giving up (failure path only)


class HeldSetp:
    """``halkins.setp`` that stops in the middle of the write until the test releases it,
    noting the thread it ran on and whether the release came (else it gave up)."""

    def __init__(self, setp) -> None:
        self.setp, self.entered, self.release = setp, threading.Event(), threading.Event()
        self.threads: list[int] = []
        self.released: list[bool] = []

    def __call__(self, pin: str, value: float) -> None:
        if not self.entered.is_set():  # the first setp of the write: held
            self.threads.append(threading.get_ident())
            self.entered.set()
            self.released.append(self.release.wait(HELD_S))
        self.setp(pin, value)


async def _entered(held: HeldSetp) -> None:
    """Wait, on the loop, for the worker to be inside the write."""
    async with asyncio.timeout(120):
        while not held.entered.is_set():
            await asyncio.sleep(0.01)


def _session(tmp_path: Path, capsys, monkeypatch) -> tuple[Session, Store, Path, HeldSetp]:
    cfg = _world(tmp_path, capsys, host="127.0.0.1", guards=GUARDS)
    pins, _ = fake_linuxcnc(tmp_path, monkeypatch)
    held = HeldSetp(halkins.setp)
    monkeypatch.setattr(halkins, "setp", held)
    conf = load_daemon_config(cfg)
    setup = conf.machines["lcnc"]
    rows = _rows(LINKS, "live")
    store = Store(conf.store_path)
    session = Session(setup, ReplayLink(rows, setup.machine), store, conf.reports_dir,
                      prepare=prepare_from_rows(rows), analyse=journal_analyse(conf.store_path),
                      after_run=after_run)
    return session, store, pins, held


async def test_the_unattended_write_runs_off_the_event_loop(tmp_path, capsys, monkeypatch):
    session, store, pins, held = _session(tmp_path, capsys, monkeypatch)
    try:
        first = session.start("cnc")  # the controller's start of shift: unattended allowed
        await _entered(held)  # the write is under way, held by the test
        # the loop is free meanwhile: it runs this code, answers the status, refuses a start
        # (the run's follow-up holds the machine) naming why
        assert held.threads != [threading.get_ident()]  # not the loop's thread
        assert session.status()["state"] == "IDLE"
        with pytest.raises(Refused, match="follow-up \\(unattended compensation\\) is under"):
            session.start("hmi")
        held.release.set()
        await session.wait()
        assert held.released == [True], "the loop was blocked: the write was never released"
        assert store.run(first).state == "DONE"
        (row,) = [r for r in cj.rows(store, "lcnc") if r.state == "applied"]
        assert row.confirmed_by == "unattended"
        assert json.loads(pins.read_text())["pins"][X] == row.values[0].new
        assert session.run_id != first  # the verification run followed
        await session.wait()
        assert not session.busy and store.run(session.run_id).state == "DONE"
    finally:
        held.release.set()
        await session.shutdown("test", report_wait_s=5)
        store.close()


async def test_a_stop_during_the_write_lets_it_end_and_starts_nothing(tmp_path, capsys,
                                                                     monkeypatch):
    session, store, pins, held = _session(tmp_path, capsys, monkeypatch)
    try:
        first = session.start("cnc")
        await _entered(held)
        stop = asyncio.ensure_future(session.shutdown("the daemon stopping", report_wait_s=5))
        for _ in range(20):  # the stop runs as far as it can: it waits on the write
            await asyncio.sleep(0)
        assert not stop.done()
        assert [r.state for r in cj.rows(store, "lcnc")] == ["applying"]
        held.release.set()
        async with asyncio.timeout(120):
            await stop
        assert held.released == [True]
        (row,) = cj.rows(store, "lcnc")  # ended, not cut: journal, pin and file agree
        assert row.state == "applied" and row.confirmed_by == "unattended"
        assert json.loads(pins.read_text())["pins"][X] == row.values[0].new
        hal = (tmp_path / "machine.hal").read_text()
        assert f"setp {X} {row.values[0].new:.6f}" in hal, hal
        assert session.run_id == first and not session.busy  # no verification run started
        assert store.run(first).state == "DONE"
    finally:
        held.release.set()
        store.close()


def test_a_halcmd_write_is_bounded_as_a_whole(tmp_path, monkeypatch):
    """Within a budget each halcmd gets what is left of it and none starts once it is spent
    (a hung halcmd is killed by its timeout, the write fails with the reason)."""
    slow = tmp_path / "halcmd"
    slow.write_text("#!/bin/sh\nsleep 30\n")
    slow.chmod(0o755)
    monkeypatch.setattr(halkins, "HALCMD", str(slow))
    with halkins.budget(0.3):
        with pytest.raises(halkins.HalError, match=r"timed out after 0\.[0-3]"):
            halkins.halcmd("getp", "x")
        with pytest.raises(halkins.HalError,
                           match=r"not started, the write's 0\.3 s budget is spent"):
            halkins.halcmd("getp", "x")
        # an inner budget never outlives the outer one
        with halkins.budget(60), pytest.raises(halkins.HalError, match="budget is spent"):
            halkins.halcmd("getp", "x")
        # putting values back: a budget of its own
        with halkins.budget(0.2, fresh=True), \
                pytest.raises(halkins.HalError, match=r"timed out after 0\.[0-2]"):
            halkins.halcmd("setp", "x", "1")
