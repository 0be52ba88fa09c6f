"""Notifications from the daemon: a run that ends WARN, FAIL or ERROR, and a morning check
not started by its deadline, sent to a webhook (JSON POST, aiohttp) and by e-mail (the
standard library's smtplib in a worker thread).

Each message is sent in a background task: a slow or dead webhook or mail server never
delays or fails a run; failures are logged and counted (``Notifier.failed``). A missed check
is judged by the daemon that owns the machine: at the deadline (local time, on the check
days) it looks in its journal for a run of that machine started since local midnight. A
daemon that is itself down cannot say so: the fleet page flags its verdict stale.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import smtplib
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from email.message import EmailMessage
from email.utils import formatdate, make_msgid
from typing import Any

import aiohttp

from daemon.notify.config import NotifyConfig
from daemon.store.journal import Store

log = logging.getLogger("rumba.notify")
_ENDED = ("IDLE", "ABORTED", "INTERRUPTED", "FAILED")  # run/phases READY_STATES


@dataclass(frozen=True)
class Notification:
    """One message: ``event`` "verdict" (``status`` WARN / FAIL / ERROR) or "missed_check"."""

    event: str
    machine: str
    status: str
    summary: str
    time_unix_s: float
    site: str = ""
    run_id: str | None = None
    reasons: list[str] = field(default_factory=list)
    report: str | None = None
    report_error: str = ""  # why the report was not written (its report job failed)

    def subject(self) -> str:
        what = ("morning check missed" if self.event == "missed_check" else self.status)
        return f"[rumba] {self.machine}: {what}"[:200]

    def text(self) -> str:
        when = time.strftime("%Y-%m-%d %H:%M %Z", time.localtime(self.time_unix_s))
        lines = [f"Machine: {self.machine}" + (f" (site {self.site})" if self.site else ""),
                 f"Status: {self.status}", f"When: {when}", f"Summary: {self.summary}"]
        if self.run_id:
            lines.append(f"Run: {self.run_id}")
        lines += [f"  - {r}" for r in self.reasons]
        if self.report:
            lines.append(f"Report: {self.report}")
        elif self.report_error:
            lines.append(f"Report: not written: {self.report_error}")
        return "\n".join(lines) + "\n"


def _one_line(s: str) -> str:
    return " ".join(str(s).split())


class Notifier:
    """Sends notifications to the configured webhook and mailbox, in background tasks."""

    def __init__(self, cfg: NotifyConfig, site: str = "") -> None:
        self.cfg, self.site = cfg, site
        self.sent = 0
        self.failed = 0
        self._tasks: set[asyncio.Task] = set()

    def notify(self, n: Notification) -> None:
        """Queue ``n`` for sending; returns at once."""
        for send in ((self._webhook,) if self.cfg.webhook_url else ()) + \
                ((self._email,) if self.cfg.email else ()):
            task = asyncio.get_running_loop().create_task(self._guarded(send, n))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _guarded(self, send: Callable[[Notification], Any], n: Notification) -> None:
        try:
            await send(n)
            self.sent += 1
        except asyncio.CancelledError:
            raise
        except Exception as e:  # any failure: logged, counted, never the run's problem
            self.failed += 1
            log.warning("notification %s of %s not sent: %s", n.event, n.machine,
                        _one_line(str(e)) or type(e).__name__)

    async def _webhook(self, n: Notification) -> None:
        headers = {"User-Agent": "rumba-cnc"}
        if self.cfg.webhook_token:
            headers["Authorization"] = f"Bearer {self.cfg.webhook_token}"
        timeout = aiohttp.ClientTimeout(total=self.cfg.webhook_timeout_s)
        last: Exception | None = None
        async with aiohttp.ClientSession(timeout=timeout, headers=headers) as http:
            for attempt in range(self.cfg.webhook_attempts):
                if attempt:
                    await asyncio.sleep(min(30.0, 2.0 ** attempt))  # backoff between retries
                try:
                    async with http.post(self.cfg.webhook_url or "", json=asdict(n)) as r:
                        if r.status < 300:
                            return
                        last = RuntimeError(f"webhook answered HTTP {r.status}")
                        if 400 <= r.status < 500 and r.status not in (408, 429):
                            break  # the receiver refuses it: retrying will not help
                except (aiohttp.ClientError, TimeoutError) as e:
                    last = e if str(e) else RuntimeError(f"webhook: {type(e).__name__}")
        raise last or RuntimeError("webhook: not sent")

    async def _email(self, n: Notification) -> None:
        await asyncio.to_thread(self._smtp_send, n)

    def _smtp_send(self, n: Notification) -> None:
        e = self.cfg.email
        assert e is not None
        msg = EmailMessage()
        msg["Subject"] = n.subject()
        msg["From"] = e.sender
        msg["To"] = ", ".join(e.to)
        msg["Date"] = formatdate(localtime=True)
        msg["Message-ID"] = make_msgid(domain="rumba")
        msg.set_content(n.text())
        with smtplib.SMTP(e.host, e.port, timeout=e.timeout_s) as smtp:
            smtp.ehlo()
            if e.starttls is not None:
                smtp.starttls(context=e.starttls)
                smtp.ehlo()
            if e.username:
                smtp.login(e.username, e.password or "")
            smtp.send_message(msg)

    async def close(self, flush_timeout_s: float = 5.0) -> None:
        """Give messages in flight a moment, then cancel what is left."""
        if self._tasks:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.gather(*self._tasks, return_exceptions=True),
                                       flush_timeout_s)
        for t in list(self._tasks):
            t.cancel()


class RunWatcher:
    """One machine's session listener: a notification when a run ends with a status the
    configuration names (a run that failed or was aborted is ERROR, as on MQTT)."""

    def __init__(self, notifier: Notifier, machine: str) -> None:
        self.notifier, self.machine = notifier, machine
        self._last: tuple | None = None
        self._waiting: dict[str, Any] | None = None  # a verdict whose report is being written

    def on_status(self, st: dict[str, Any]) -> None:
        # the report is written after the run's end; the notification waits for it
        # (its path), and is sent without it when a new run starts first
        w = self._waiting
        if w is not None and (st["run_id"] != w["run_id"] or (st["verdict"] or {}).get(
                "report_state") != "writing"):
            self._waiting = None
            self._send(st if st["run_id"] == w["run_id"] else w)
        key = (st["state"], st["run_id"])
        previous, self._last = self._last, key
        if previous is None or key == previous or not st["run_id"]:
            return
        if previous[0] in _ENDED or st["state"] not in _ENDED:
            return
        v = st.get("verdict") or {}
        if st["state"] == "IDLE" and v.get("report_state") == "writing":
            self._waiting = {**st, "verdict": dict(v)}
            return
        self._send(st)

    def _send(self, st: dict[str, Any]) -> None:
        if st.get("job") == "map" and st["state"] == "IDLE":
            return  # a map done is no verdict of the machine (its figures: the map's JSON)
        v = st.get("verdict") or {}
        done = st["state"] == "IDLE" and v.get("status")
        status = v["status"] if done else "ERROR"
        if status not in self.notifier.cfg.on:
            return
        self.notifier.notify(Notification(
            "verdict", self.machine, status,
            v.get("summary", "") if done else f"run {st['state'].lower()}: {st['reason']}",
            time.time(), self.notifier.site, st["run_id"],
            list(v.get("reasons", [])) if done else [], v.get("report"),
            # the report job's end (daemon/store/report_jobs.py), never the run's reason
            str(v.get("report_error") or "") if v.get("report_state") == "failed" else ""))


def deadline_on(day_t: float, hh: int, mm: int) -> float:
    """``hh:mm`` local time on the local day of ``day_t`` (DST-aware, via mktime)."""
    t = time.localtime(day_t)
    return time.mktime((t.tm_year, t.tm_mon, t.tm_mday, hh, mm, 0, 0, 0, -1))


def missed_checks(cfg: NotifyConfig, store: Store, now: float) -> list[str]:
    """The machines whose deadline of today has passed at ``now`` (a check day) without a run
    started since local midnight."""
    if time.localtime(now).tm_wday not in cfg.days:
        return []
    midnight = deadline_on(now, 0, 0)
    out = []
    for machine, (hh, mm) in cfg.deadlines.items():
        if now < deadline_on(now, hh, mm):
            continue
        runs = store.runs(machine, 50)
        if not any(midnight <= r.started_at for r in runs):
            out.append(machine)
    return out


async def morning_loop(notifier: Notifier, store: Store,
                       busy: Callable[[str], bool]) -> None:
    """Forever: at each machine's deadline, announce a missed check (once per day)."""
    cfg = notifier.cfg
    announced: set[tuple[str, float]] = set()
    while True:
        now = time.time()
        for m in missed_checks(cfg, store, now):
            day = deadline_on(now, 0, 0)
            if (m, day) not in announced and not busy(m):
                announced.add((m, day))
                hh, mm = cfg.deadlines[m]
                notifier.notify(Notification(
                    "missed_check", m, "MISSED", f"no start-of-shift check of {m} started "
                    f"today by {hh:02d}:{mm:02d}", now, notifier.site))
        announced = {a for a in announced if a[1] >= deadline_on(now, 0, 0)}
        # the next deadline (today's or tomorrow's), re-checked at least every 10 min
        upcoming = [d for hh, mm in cfg.deadlines.values()
                    for d in (deadline_on(now, hh, mm), deadline_on(now + 86400, hh, mm))
                    if d > now]
        await asyncio.sleep(max(1.0, min([600.0, *(d - now + 0.5 for d in upcoming)])))
