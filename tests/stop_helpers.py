"""Helpers of the stop matrix (tests/test_stop_matrix.py, tests/test_stop_signals.py): a short
plan, a daemon.yaml for one simulated CNC, a session whose steps can be held in a chosen phase,
and waits on events (never on a clock guess) that fail at once with the run's reason."""

from __future__ import annotations

import asyncio
import contextlib
import sqlite3
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from daemon.analysis import pipeline
from daemon.run.session import Session, State
from tests.daemon_helpers import CONFIG

SHORT_PLAN = {  # 4 poses × 4 balls × 5 touches: the fewest that still identify (2 do not)
    "name": "stop-matrix-4poses", "stylus_diameter_mm": 6,
    "poses": [[0, 0], [30, 60], [0, 180], [-30, 300]],
    "feeds": {"probe_mm_min": 300, "approach_mm_min": 2000}, "standoff_mm": 2,
    "overtravel_mm": 2, "clearance_mm": 10,
}
HELD = 30.0  # the longest a held step waits for its release (a safety net, never reached)


def write_config(tmp: Path, link: dict[str, Any], *, plan: dict | None = None,
                 hmi_port: int | None = None) -> Path:
    """daemon.yaml for machine ``mill1`` (thesis machine, Fanuc) on ``link``."""
    plan_path = tmp / "plan.yaml"
    plan_path.write_text(yaml.safe_dump(plan or SHORT_PLAN), encoding="utf-8")
    hmi: dict[str, Any] = {"enabled": False}
    if hmi_port is not None:
        hmi = {"enabled": True, "port": hmi_port, "token": "t0k3n-for-tests-0123456789"}
    doc = {
        "store": {"path": str(tmp / "journal.sqlite")}, "reports_dir": str(tmp / "reports"),
        "hmi": hmi,
        "machines": [{
            "name": "mill1", "machine": str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
            "artefact": str(CONFIG / "artefacts/thesis_4ball.yaml"), "plan": str(plan_path),
            "dialect": "fanuc", "link": link, "touch_timeout_s": 30,
            "tolerances": {"default_rotation_urad": {"warn": 400, "fail": 800},
                           "default_translation_um": {"warn": 1500, "fail": 3000},
                           "volumetric_max_um": {"warn": 2000, "fail": 4000}},
        }],
    }
    path = tmp / "daemon.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    return path


class Hold:
    """Holds a run in one phase: the step signals ``reached`` and waits to be released (a
    worker thread for PREPARE / IDENTIFY / REPORT, a coroutine for WRITE-BACK)."""

    def __init__(self, phase: str | None) -> None:
        self.phase = phase
        self.reached = asyncio.Event()
        self.loop = asyncio.get_running_loop()
        self._release = threading.Event()
        self.go_on = asyncio.Event()  # CAPTURE: let the link read on (a CNC reset, a lost link)

    def release(self) -> None:
        self._release.set()
        self.go_on.set()

    def in_thread(self, phase: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def held(*a: Any, **kw: Any) -> Any:
            if self.phase == phase and not self.reached.is_set():
                self.loop.call_soon_threadsafe(self.reached.set)
                self._release.wait(HELD)  # the run is stopped meanwhile: its result is dropped
            return fn(*a, **kw)
        return held

    def write_back(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        async def held(verdict: Any) -> None:
            if self.phase == "WRITE-BACK" and not self.reached.is_set():
                self.reached.set()
                await asyncio.sleep(HELD)  # cancelled by the stop
            await fn(verdict)
        return held

    def capture(self, run: Callable[..., Any]) -> Callable[..., Any]:
        """The link's ``run``, held after its first hit while the program runs on the CNC."""
        def held(job: Any) -> Any:
            async def hits() -> Any:
                async with contextlib.aclosing(run(job)) as agen:
                    async for hit in agen:
                        yield hit
                        if self.phase == "CAPTURE" and not self.reached.is_set():
                            self.reached.set()
                            with contextlib.suppress(TimeoutError):
                                await asyncio.wait_for(self.go_on.wait(), HELD)
            return hits()
        return held


def held_session(setup: Any, link: Any, store: Any, reports: Path, hold: Hold,
                 monkeypatch: Any) -> Session:
    """A session whose PREPARE / IDENTIFY / REPORT / WRITE-BACK step ``hold`` can stop in."""
    from daemon.reports import report

    monkeypatch.setattr(report, "write_report", hold.in_thread("REPORT", report.write_report))
    s = Session(setup, link, store, reports,
                prepare=hold.in_thread("PREPARE", pipeline.prepare),
                analyse=hold.in_thread("IDENTIFY", pipeline.analyse))
    link.write_verdict = hold.write_back(link.write_verdict)
    link.run = hold.capture(link.run)
    return s


async def until_reached(session: Session, hold: Hold, timeout_s: float = 60.0) -> None:
    """Wait until the run is held in its phase; fail at once with the reason if it ended."""
    async with asyncio.timeout(timeout_s):
        ended = asyncio.ensure_future(session.wait())
        reached = asyncio.ensure_future(hold.reached.wait())
        done, _ = await asyncio.wait({ended, reached}, return_when=asyncio.FIRST_COMPLETED)
        if reached not in done:
            reached.cancel()
            raise AssertionError(f"run {session.run_id} ended {session.state} before "
                                 f"{hold.phase}: {session.reason}")
        ended.cancel()


async def until_first_hit(session: Session, timeout_s: float = 60.0) -> None:
    """Wait for the run's first journaled hit: the controller took the new program."""
    q = session.subscribe()
    try:
        async with asyncio.timeout(timeout_s):
            while True:
                st = await q.get()
                if st["done"] >= 1 and st["run_id"] == session.run_id:
                    return
                if st["state"] in (State.FAILED, State.ABORTED):
                    raise AssertionError(f"next run {st['state']}: {st['reason']}")
    finally:
        session.unsubscribe(q)


def latest_run(db: Path) -> tuple[str, str, str, int] | None:
    """(run id, state, reason, hits) of the journal's latest run, read as ``rumba history``
    does (a read-only WAL reader beside the writing process); None before there is one."""
    if not db.exists():
        return None
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        row = con.execute("SELECT id, state, COALESCE(reason, '') FROM runs "
                          "ORDER BY started_at DESC LIMIT 1").fetchone()
        if row is None:
            return None
        hits = con.execute("SELECT COUNT(*) FROM hits WHERE run_id=?", (row[0],)).fetchone()
        return row[0], row[1], row[2], hits[0]
    except sqlite3.OperationalError:  # the schema is being created
        return None
    finally:
        con.close()
