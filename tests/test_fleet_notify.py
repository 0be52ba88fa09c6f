"""Notifications from a real daemon run: a FAIL verdict reaches a local webhook receiver
(aiohttp, with its bearer token) and a local SMTP sink (asyncio, minimal SMTP, AUTH PLAIN
with the password from its file); a PASS sends nothing; a dead webhook and mail server never
fail the run; the missed morning check from the journal, on time and check days; config
errors name their key."""

from __future__ import annotations

import asyncio
import base64
import time
from email import message_from_bytes

import pytest
from aiohttp import web

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from contracts.yaml_files import ConfigError
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.notify.config import NotifyFile, load_notify
from daemon.notify.notifier import missed_checks
from daemon.service.service import Service
from daemon.store.journal import Store
from simulators.fleet_peers import free_port
from tests.fleet_helpers import until

HOOK_TOKEN = "hook-t0k3n-0123456789"
MAIL_PASSWORD = "mail-passw0rd-0123456789"


class SmtpSink:
    """A minimal SMTP server (RFC 5321 subset: EHLO, AUTH PLAIN, MAIL, RCPT, DATA, QUIT)."""

    def __init__(self) -> None:
        self.messages: list[dict] = []
        self.server: asyncio.Server | None = None
        self.port = 0

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._client, "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]

    async def _client(self, r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        def say(line: str) -> None:
            w.write(line.encode() + b"\r\n")

        msg: dict = {"rcpt": []}
        say("220 sink ESMTP")
        while line := (await r.readline()).decode().rstrip("\r\n"):
            verb = line.split(" ", 1)[0].upper()
            if verb in ("EHLO", "HELO"):
                say("250-sink")
                say("250 AUTH PLAIN")
            elif verb == "AUTH":
                msg["auth"] = base64.b64decode(line.split()[2]).split(b"\0")
                say("235 ok")
            elif verb == "MAIL":
                msg["from"] = line
                say("250 ok")
            elif verb == "RCPT":
                msg["rcpt"].append(line)
                say("250 ok")
            elif verb == "DATA":
                say("354 go")
                data = b""
                while (chunk := await r.readline()) != b".\r\n":
                    data += chunk
                msg["data"] = data
                self.messages.append(msg)
                say("250 queued")
            elif verb == "QUIT":
                say("221 bye")
                break
            else:
                say("502 no")
            await w.drain()
        await w.drain()
        w.close()

    def close(self) -> None:
        assert self.server is not None
        self.server.close()


async def webhook_receiver() -> tuple[web.AppRunner, str, list]:
    got: list = []

    async def hook(request: web.Request) -> web.Response:
        got.append((request.headers.get("Authorization"), await request.json()))
        return web.json_response({"ok": True})

    app = web.Application()
    app.router.add_post("/hook", hook)
    runner = web.AppRunner(app)
    await runner.setup()
    await web.TCPSite(runner, "127.0.0.1", 0).start()
    return runner, f"http://127.0.0.1:{runner.addresses[0][1]}/hook", got


def secret(tmp_path, name: str, text: str) -> str:
    p = tmp_path / name
    p.write_text(text)
    p.chmod(0o600)
    return str(p)


def notify_yaml(tmp_path, hook_url: str, smtp_port: int, extra: str = "") -> str:
    return (f"notify:\n  webhook: {{url: '{hook_url}', attempts: 1, token_file: "
            f"{secret(tmp_path, 'hook.token', HOOK_TOKEN)}}}\n"
            f"  email: {{host: 127.0.0.1, port: {smtp_port}, from: rumba@shop.example, "
            f"to: [qa@shop.example, it@shop.example], username: rumba, password_file: "
            f"{secret(tmp_path, 'mail.pw', MAIL_PASSWORD)}, timeout_s: 5}}\n{extra}")


async def run_once(tmp_path, notify: str, *, fail: bool) -> tuple[Service, dict]:
    path = write_daemon_yaml(tmp_path, extra_top=notify)
    if fail:  # limits no machine meets: the verdict is FAIL
        path.write_text(path.read_text().replace("{warn: 40, fail: 80,",
                                                 "{warn: 0.001, fail: 0.002,"))
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    run_id = svc.trigger("mill1", "cli")
    session = svc.sessions["mill1"]

    def ended() -> bool:
        st = session.status()
        return st["run_id"] == run_id and st["state"] in ("IDLE", "FAILED", "ABORTED",
                                                           "INTERRUPTED")

    await until(ended, 120, "the run's end")
    return svc, session.status()


async def test_fail_verdict_is_sent_to_webhook_and_mail(tmp_path):
    sink = SmtpSink()
    await sink.start()
    runner, url, got = await webhook_receiver()
    svc, st = await run_once(tmp_path, notify_yaml(tmp_path, url, sink.port), fail=True)
    try:
        assert st["verdict"]["status"] == "FAIL"
        await until(lambda: got and sink.messages, 30, "webhook and mail")
        auth, body = got[0]
        assert auth == f"Bearer {HOOK_TOKEN}"
        assert (body["event"], body["machine"], body["status"], body["run_id"]) == (
            "verdict", "mill1", "FAIL", st["run_id"])
        assert body["reasons"] and body["report"].endswith(".html")
        m = sink.messages[0]
        assert m["auth"][1:] == [b"rumba", MAIL_PASSWORD.encode()]
        assert len(m["rcpt"]) == 2 and "qa@shop.example" in m["rcpt"][0]
        mail = message_from_bytes(m["data"])
        assert mail["Subject"] == "[rumba] mill1: FAIL" and mail["To"].count("@") == 2
        assert f"Run: {st['run_id']}" in mail.get_payload(decode=True).decode()
    finally:
        await svc.stop()
        await runner.cleanup()
        sink.close()


async def test_pass_sends_nothing_and_dead_servers_never_fail_a_run(tmp_path):
    runner, url, got = await webhook_receiver()
    (tmp_path / "a").mkdir()
    svc, st = await run_once(tmp_path / "a", notify_yaml(tmp_path, url, free_port()),
                             fail=False)
    await svc.stop()
    assert st["verdict"]["status"] == "PASS" and got == []
    assert svc.fleet.notifier.sent == 0 and svc.fleet.notifier.failed == 0
    await runner.cleanup()
    # nothing listens on either port: the FAIL run still ends with its verdict
    (tmp_path / "b").mkdir()
    svc, st = await run_once(tmp_path / "b", notify_yaml(
        tmp_path, f"http://127.0.0.1:{free_port()}/hook", free_port()), fail=True)
    try:
        assert st["state"] == "IDLE" and st["verdict"]["status"] == "FAIL"
        await until(lambda: svc.fleet.notifier.failed == 2, 30, "both failures counted")
        assert svc.fleet.notifier.sent == 0
    finally:
        await svc.stop()


async def test_missed_morning_check_from_the_daemon(tmp_path):
    """Deadline a minute ago, a fresh journal: the daemon announces the missed check."""
    runner, url, got = await webhook_receiver()
    now = time.localtime()
    midnight = time.mktime((now.tm_year, now.tm_mon, now.tm_mday, 0, 0, 0, 0, 0, -1))
    due = time.strftime("%H:%M", time.localtime(max(time.time() - 60, midnight)))
    extra = (f"notify:\n  webhook: {{url: '{url}', attempts: 1}}\n  morning_check_by: '{due}'\n"
             "  morning_check_days: [mon, tue, wed, thu, fri, sat, sun]\n")
    path = write_daemon_yaml(tmp_path, extra_top=extra)
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        await until(lambda: got, 30, "missed-check notification")
        body = got[0][1]
        assert (body["event"], body["machine"], body["status"]) == ("missed_check", "mill1",
                                                                     "MISSED")
        assert due in body["summary"]
    finally:
        await svc.stop()
        await runner.cleanup()


def test_missed_checks_rule(tmp_path):
    cfg = load_notify(NotifyFile.model_validate({
        "webhook": {"url": "http://127.0.0.1:9/x"}, "morning_check_by": "07:00",
        "morning_check_by_machine": {"m3": None}}), tmp_path, "notify", ["m1", "m2", "m3"],
        lambda p, w: "")
    store = Store(tmp_path / "j.sqlite")
    monday = time.mktime((2026, 11, 23, 0, 0, 0, 0, 0, -1))  # a Monday, local midnight
    h = 3600.0
    store.new_run("R-yesterday", "m1", "shift", started_at=monday - 5 * h)
    store.new_run("R-today", "m2", "shift", started_at=monday + 6 * h)
    assert missed_checks(cfg, store, monday + 6.9 * h) == []  # before the deadline
    assert missed_checks(cfg, store, monday + 7.5 * h) == ["m1"]  # m3 has no deadline
    assert missed_checks(cfg, store, monday + 5 * 24 * h + 8 * h) == []  # Saturday
    store.close()


@pytest.mark.parametrize("notify, why", [
    ("notify: {webhook: {url: 'http://x/'}, bogus: 1}", "bogus"),
    ("notify: {webhook: {url: 'http://x/'}, morning_check_by: '7am'}", "HH:MM"),
    ("notify: {morning_check_by: '07:00'}", "a 'webhook', an 'email'"),
    ("notify: {email: {host: h, from: 'a@b\\r\\nBcc: x@y', to: [q@r]}}", "one e-mail address"),
    ("notify: {webhook: {url: 'ftp://x/'}}", "http"),
    ("notify: {webhook: {url: 'http://x/'}, morning_check_by_machine: {nope: '07:00'}}",
     "morning_check_by_machine.nope: not a configured machine"),
])
def test_notify_config_errors_name_the_key(tmp_path, notify, why):
    path = write_daemon_yaml(tmp_path, extra_top=notify)
    with pytest.raises(ConfigError, match=why) as e:
        load_daemon_config(path)
    assert "notify" in str(e.value)


def test_the_notification_waits_for_the_report_and_is_never_lost():
    """The report is written after the run's end. The FAIL notification waits for
    it (its path), goes out without it when the report failed, and is sent without it when a
    new run starts before the report was written (never lost)."""
    from types import SimpleNamespace

    from daemon.notify.notifier import RunWatcher

    sent: list = []
    notifier = SimpleNamespace(cfg=SimpleNamespace(on=("FAIL",)), site="s", notify=sent.append)
    w = RunWatcher(notifier, "mill1")  # type: ignore[arg-type]

    def st(state: str, run_id: str, report_state: str | None = None, report: str | None = None):
        v = {"status": "FAIL", "summary": "x", "reasons": ["r"]} if state == "IDLE" else None
        if v is not None and report_state:
            v |= {"report_state": report_state, **({"report": report} if report else {})}
            if report_state == "failed":
                v["report_error"] = "OSError: disk full"
        return {"state": state, "run_id": run_id, "reason": "", "verdict": v}

    for s in (st("IDLE", ""), st("JUDGE", "A"), st("IDLE", "A", "writing")):
        w.on_status(s)
    assert sent == []  # the run ended; its report is being written
    w.on_status(st("IDLE", "A", "written", "/r/A.html"))
    assert [(n.run_id, n.report) for n in sent] == [("A", "/r/A.html")]
    for s in (st("JUDGE", "B"), st("IDLE", "B", "writing"), st("IDLE", "B", "failed")):
        w.on_status(s)
    assert [(n.run_id, n.report, n.report_error) for n in sent[1:]] == \
        [("B", None, "OSError: disk full")]
    assert "Report: not written: OSError: disk full" in sent[1].text()  # says why
    for s in (st("JUDGE", "C"), st("IDLE", "C", "writing"), st("PREPARE", "D")):
        w.on_status(s)  # D started before C's report was written: C is sent all the same
    assert [(n.run_id, n.status, n.report, n.report_error) for n in sent[2:]] == \
        [("C", "FAIL", None, "")]
