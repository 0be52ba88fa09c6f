"""Helpers of the stop tests (tests/test_stop_*.py): a short plan, a daemon.yaml for one
simulated CNC, a session whose steps can be held in a chosen phase, a ``rumba`` process, and
waits on events (never on a clock guess) that fail at once with the run's reason."""

from __future__ import annotations

import asyncio
import contextlib
import os
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from benchmarks.rigs.daemon_helpers import CONFIG
from daemon.analysis import pipeline
from daemon.run.phases import STOPPED_STATES
from daemon.run.session import Session, State

SHORT_PLAN = {  # 4 poses × 4 balls × 5 touches: the fewest that still identify (2 do not)
    "name": "stop-matrix-4poses", "stylus_diameter_mm": 6,
    "poses": [[0, 0], [30, 60], [0, 180], [-30, 300]],
    "feeds": {"probe_mm_min": 300, "approach_mm_min": 2000}, "standoff_mm": 2,
    "overtravel_mm": 2, "clearance_mm": 10,
}
HELD = 30.0  # the longest a held step waits for its release (a safety net, never reached)
ROOT = Path(__file__).resolve().parents[1]


def rumba_process(*argv: str, **kw: Any) -> subprocess.Popen:
    """``rumba ARGV`` as its own process (text pipes unless ``kw`` says otherwise, unbuffered),
    the way a shell starts it."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("RUMBA_DEBUG", None)
    opts: dict[str, Any] = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True,
                            **kw}
    return subprocess.Popen([sys.executable, "-m", "daemon.cli", *argv], cwd=ROOT, env=env,
                            **opts)


def write_config(tmp: Path, link: dict[str, Any], *, plan: dict | None = None,
                 hmi_port: int | None = None, dialect: str = "fanuc") -> Path:
    """daemon.yaml for machine ``mill1`` (thesis machine, Fanuc unless ``dialect``) on
    ``link``."""
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
            "dialect": dialect, "link": link, "touch_timeout_s": 30,
            "tolerances": {"default_rotation_urad": {"warn": 400, "fail": 800},
                           "default_translation_um": {"warn": 1500, "fail": 3000},
                           "volumetric_max_um": {"warn": 2000, "fail": 4000}},
        }],
    }
    path = tmp / "daemon.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    return path


REPORT_JOB = "report job"
"""Not a phase: the report worker after the run's end (daemon/run/report_job.py), held as one."""


class Hold:
    """Holds a run in one phase, or its report job: the step signals ``reached`` and waits to
    be released (a worker thread for PREPARE / IDENTIFY / the report job, a coroutine for
    WRITE-BACK)."""

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

    def write_back(self, fn: Callable[..., Any], in_phase: Callable[[], bool]
                   ) -> Callable[..., Any]:
        """``in_phase``: the run is in WRITE-BACK (the ERROR a stopped run writes back at its
        end is not that phase)."""
        async def held(verdict: Any) -> None:
            if self.phase == "WRITE-BACK" and in_phase() and not self.reached.is_set():
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
    """A session whose PREPARE / IDENTIFY / WRITE-BACK step, or report job after the run's
    end, ``hold`` can stop in."""
    from daemon.reports import report

    monkeypatch.setattr(report, "write_report", hold.in_thread(REPORT_JOB, report.write_report))
    s = Session(setup, link, store, reports,
                prepare=hold.in_thread("PREPARE", pipeline.prepare),
                analyse=hold.in_thread("IDENTIFY", pipeline.analyse))
    link.write_verdict = hold.write_back(link.write_verdict,
                                         lambda: s.state == State.WRITE_BACK)
    link.run = hold.capture(link.run)
    return s


async def until_reached(session: Session, hold: Hold, timeout_s: float = 60.0,
                        diagnose: Callable[[], str] = str) -> None:
    """Wait until the run is held in its phase; fail at once with the reason if it ended
    (and what ``diagnose`` says of the controller)."""
    async with asyncio.timeout(timeout_s):
        ended = asyncio.ensure_future(session.wait())
        reached = asyncio.ensure_future(hold.reached.wait())
        done, _ = await asyncio.wait({ended, reached}, return_when=asyncio.FIRST_COMPLETED)
        if reached not in done:
            reached.cancel()
            raise AssertionError(f"run {session.run_id} ended {session.state} before "
                                 f"{hold.phase}: {session.reason} ({diagnose()})")
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
                if st["state"] in STOPPED_STATES:
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


def until_capturing(proc: subprocess.Popen, db: Path, not_run: str | None = None,
                    timeout_s: float = 120.0) -> str:
    """Wait for a first journaled hit of a run other than ``not_run`` (the run is capturing);
    return its id. Fails at once, with its stderr, if ``proc`` ends first."""
    deadline = time.monotonic() + timeout_s
    while True:
        row = latest_run(db)
        if row and row[0] != not_run and row[3] >= 1:
            return row[0]
        if proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr else ""
            raise AssertionError(f"rumba {proc.args[3]} ended ({proc.returncode}) before "
                                 f"capturing: {err}")
        assert time.monotonic() < deadline, f"no hit journaled in {timeout_s:g} s"
        time.sleep(0.05)


class TcpCut:
    """A TCP relay between rumba and a controller whose cable can be pulled: ``cut`` resets
    every connection and stops listening (the network gone: a new connection is refused),
    ``restore`` listens again on the same port."""

    def __init__(self, target_port: int, host: str = "127.0.0.1") -> None:
        self.host, self.target_port, self.port = host, target_port, 0
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    async def start(self) -> int:
        self._server = await asyncio.start_server(self._serve, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        return self.port

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            up_r, up_w = await asyncio.open_connection(self.host, self.target_port)
        except OSError:
            writer.transport.abort()
            return
        self._writers |= {writer, up_w}

        async def pump(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
            with contextlib.suppress(OSError, asyncio.CancelledError):
                while data := await r.read(65536):
                    w.write(data)
                    await w.drain()
            w.transport.abort()

        await asyncio.gather(pump(reader, up_w), pump(up_r, writer))
        self._writers -= {writer, up_w}

    async def cut(self) -> None:
        assert self._server is not None
        self._server.close()
        for w in list(self._writers):
            w.transport.abort()
        await self._server.wait_closed()

    async def restore(self) -> None:
        await self.start()
