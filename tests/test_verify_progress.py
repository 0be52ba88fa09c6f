"""`rumba verify`'s progress bar label in each phase of a run (local and ``--daemon``): the run's
phases by their HMI names, then its end as the journal names it (DONE, ABORTED, …), "report
being written…" while the report job runs after a DONE; never a made-up REPORT phase."""

from __future__ import annotations

import io
import json
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import aiohttp
from aiohttp import web
from rich.console import Console
from rich.progress import Progress

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.cli.commands.verify import verify
from daemon.cli.commands.verify_daemon import bar_fields, follow_run


def _status(state: str, done: int = 0, *, run_id: str = "R1", machine: str = "mill1",
            report_state: str | None = None, eta_s: float | None = None) -> dict[str, Any]:
    busy = state not in ("IDLE", "ABORTED", "FAILED", "INTERRUPTED")
    verdict = None if report_state is None else {"status": "PASS",
                                                 "report_state": report_state}
    return {"machine": machine, "run_id": run_id, "state": state, "done": done, "total": 80,
            "busy": busy, "eta_s": eta_s, "verdict": verdict, "reason": ""}


class RecordingProgress(Progress):
    """A real rich Progress that also keeps every (label, trailing text) it was given."""

    def __init__(self) -> None:
        super().__init__(console=Console(file=io.StringIO()), disable=True)
        self.seen: list[tuple[str, str]] = []

    def update(self, task_id, **kw) -> None:  # type: ignore[no-untyped-def,override]
        super().update(task_id, **kw)
        fields = self.tasks[0].fields
        self.seen.append((fields["state"], fields["eta"]))


@asynccontextmanager
async def sse(statuses: list[dict[str, Any]]) -> AsyncIterator[str]:
    """A loopback HTTP server whose /api/events streams ``statuses`` as the HMI does."""

    async def events(request: web.Request) -> web.StreamResponse:
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream"})
        await resp.prepare(request)
        await resp.write(b": keep-alive\n\n")
        for st in statuses:
            await resp.write(f"event: status\ndata: {json.dumps(st)}\n\n".encode())
        return resp

    app = web.Application()
    app.router.add_get("/api/events", events)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    try:
        port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        yield f"http://127.0.0.1:{port}/api/events"
    finally:
        await runner.cleanup()


async def _follow(statuses: list[dict[str, Any]]) -> tuple[dict[str, Any], list]:
    bar = RecordingProgress()
    task = bar.add_task("R1", total=None, state="PREPARE", eta="")
    async with sse(statuses) as url, aiohttp.ClientSession() as http, \
            http.get(url) as events:
        last = await follow_run(events, "mill1", "R1", bar, task)
    return last, bar.seen


async def test_daemon_bar_names_each_phase_then_done_while_the_report_is_written():
    last, seen = await _follow([
        _status("PREPARE", eta_s=200.0),
        _status("CAPTURE", 40, machine="mill2"),  # another machine's run: not shown
        _status("CAPTURE", 40, eta_s=65.0),
        _status("IDENTIFY", 80), _status("JUDGE", 80), _status("WRITE-BACK", 80),
        _status("IDLE", 80, report_state="writing"),
        _status("IDLE", 80, report_state="written"),
        _status("PREPARE", run_id="R2"),  # the next run: the CLI has returned before it
    ])
    assert seen == [("PREPARE", "time left: 3 min 20 s"), ("CAPTURE", "time left: 1 min 05 s"),
                    ("IDENTIFY", "time left: —"), ("JUDGE", "time left: —"),
                    ("WRITE-BACK", "time left: —"), ("DONE", "report being written…"),
                    ("DONE", "")]
    assert last["verdict"]["report_state"] == "written"


async def test_daemon_bar_shows_a_run_that_ended_without_verdict_by_its_end():
    last, seen = await _follow([_status("CAPTURE", 12), _status("ABORTED", 12),
                                _status("IDLE", 12)])
    assert [s for s, _ in seen] == ["CAPTURE", "ABORTED"] and last["state"] == "ABORTED"
    # a report that failed ends the wait as one written does, the label DONE
    assert bar_fields(_status("IDLE", 80, report_state="failed")) == {"state": "DONE",
                                                                       "eta": ""}


async def test_local_verify_bar_ends_on_done_not_on_the_sessions_idle(tmp_path):
    path = write_daemon_yaml(tmp_path)
    rows = thesis_rows(thesis_setup())
    out = io.StringIO()
    code = await verify(str(path), "mill1", console=Console(file=out, width=120),
                        link_factory=lambda s: ReplayLink(rows, s.machine),
                        prepare=prepare_from_rows(rows))
    assert code == 0
    last = [ln for ln in out.getvalue().splitlines() if "touches" in ln][-1]
    assert last.split()[0] == "DONE" and "140/140 touches" in last, out.getvalue()
