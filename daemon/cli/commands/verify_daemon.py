"""``rumba verify --daemon``'s side of the daemon's HMI API: follow one run's status events to its
end (the progress bar's label for each phase, shared with the local ``rumba verify``), and abort
that run (Ctrl-C, SIGTERM) waiting until the daemon reports it ended."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import ssl
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from daemon.cli.main import UserError

if TYPE_CHECKING:
    import aiohttp
    from rich.progress import Progress, TaskID


async def follow_run(events: aiohttp.ClientResponse, machine: str, run_id: str,
                     bar: Progress, task: TaskID,
                     on_status: Callable[[dict[str, Any]], None] | None = None
                     ) -> dict[str, Any]:
    """The run's status events (``/api/events``) shown on ``bar`` (and handed to
    ``on_status``: a map job's prompts) until the daemon reports the run ended; returns that
    last status."""
    async for line in events.content:
        if not line.startswith(b"data: "):
            continue
        st = json.loads(line[6:])
        if st["machine"] != machine or st["run_id"] != run_id:
            continue
        bar.update(task, total=st["total"] or None, completed=st["done"], **bar_fields(st))
        if on_status is not None:
            on_status(st)
        if not st["busy"] and not report_writing(st):
            return st  # after the run's end, until its report is written (or not)
    raise UserError(f"the daemon closed its event stream before run {run_id} ended "
                    "(daemon stopped?); see `rumba history`")


async def abort_on_daemon(http: aiohttp.ClientSession, base: str, machine: str, run_id: str,
                          sig: signal.Signals, follow: asyncio.Task, ctx: ssl.SSLContext | None
                          ) -> dict[str, Any]:
    """Abort ``run_id`` on the daemon, naming ``sig``: the answer comes once the run has ended
    (controller reset, journal row ABORTED); a run that ended meanwhile is followed to the end
    its events report. Returns the run's final status."""
    url = base + f"api/machines/{machine}/abort"
    try:
        r = await http.post(url, params={"by": sig.name, "run_id": run_id}, ssl=ctx)
        body = await r.json()
    except BaseException:
        follow.cancel()
        raise
    if r.status == 200 and body.get("run_id") == run_id and not body.get("busy"):
        follow.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await follow
        return body
    if r.status == 409:  # it ended on its own before the abort reached it: its own end
        return await follow
    follow.cancel()
    raise UserError(f"run {run_id} could not be aborted on the daemon: "
                    f"{body.get('error', f'HTTP {r.status}')}; it may still be running "
                    f"(HMI Abort stops it)")


def report_writing(st: dict[str, Any]) -> bool:
    """The run ended with its verdict and its report is still being written."""
    return st["state"] == "IDLE" and (st.get("verdict") or {}).get("report_state") == "writing"


def bar_fields(st: dict[str, Any]) -> dict[str, str]:
    """The progress bar's label and trailing text (``rumba verify``, local or ``--daemon``):
    while the run runs, its phase as the HMI names it (PREPARE … WRITE-BACK) and the time left;
    once it ended, its end as the journal and ``rumba history`` name it: DONE (the session is
    IDLE again, the verdict on the CNC; "report being written…", the HMI's words, until the
    report is there) or ABORTED, FAILED, INTERRUPTED. No phase is called REPORT: the report is
    written after the run, the machine already free."""
    if st["busy"]:
        return {"state": st["state"], "eta": eta_text(st)}
    if st["state"] == "IDLE":
        return {"state": "DONE", "eta": "report being written…" if report_writing(st) else ""}
    return {"state": st["state"], "eta": ""}


def eta_text(st: dict[str, Any]) -> str:
    """The status's time left as the progress bar shows it."""
    eta = st.get("eta_s")
    if eta is None:
        return "time left: —"
    m, s = divmod(int(eta), 60)
    return f"time left: {m} min {s:02d} s" if m else f"time left: {s} s"
