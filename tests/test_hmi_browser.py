"""The operator page in headless Chromium (peer), as an operator sees it: the last verdict's
date (local time) and age, flagged stale past ``hmi.stale_after_h``; the trend, one chart per
link error on its own unit axis with its limits; the "Last runs" row of a running run showing
the same touch count as the progress bar; the PDF of a finished run; no sideways overflow on a
390 px phone; a refused start shown whether its answer is JSON or a proxy's text page."""

from __future__ import annotations

import asyncio
import datetime
import time
from zoneinfo import ZoneInfo

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from benchmarks.rigs.report_helpers import journal_run
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.run.phases import END_READS
from daemon.service.service import Service
from tests.browser import chromium, tick_preflight

pytestmark = [pytest.mark.peer]
TOKEN = "t0k3n-for-browser-0123456789"
TZ = "America/Chicago"  # not the test machine's zone: the page must use the browser's


async def start_service(tmp_path, *, delay_s: float = 0.0, hmi_extra: str = "") -> Service:
    path = write_daemon_yaml(tmp_path, token=TOKEN)
    path.write_text(path.read_text().replace(f"token: {TOKEN}}}",
                                             f"token: {TOKEN}{hmi_extra}}}"))
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine,
                                                                  delay_s=delay_s),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    return svc


def past_run(svc: Service, run_id: str, seed: int, ended_ago_s: float) -> float:
    """A journaled run (analysis, verdict) that ended ``ended_ago_s`` ago; its end time."""
    started = time.time() - ended_ago_s - 240
    journal_run(svc.store, thesis_setup(), run_id, seed, started)
    ended = time.time() - ended_ago_s
    svc.store.db.execute("UPDATE runs SET ended_at=? WHERE id=?", (ended, run_id))
    return ended


async def test_verdict_date_age_stale_and_trend_axes(tmp_path):
    svc = await start_service(tmp_path, hmi_extra=", stale_after_h: 2")
    try:
        past_run(svc, "R1-older", 1, 27 * 3600)
        ended = past_run(svc, "R2-latest", 2, 3 * 3600 + 600)  # 3 h 10 min ago
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.call("Emulation.setTimezoneOverride", sid, timezoneId=TZ)
            await cdp.sign_in(sid, svc.hmi_url, TOKEN)
            card = "document.querySelector('.machine')"
            await cdp.wait_for(sid, f"{card}.querySelector('.badge').textContent === 'PASS'")
            when = await cdp.eval(sid, f"[{card}.querySelector('.when time').textContent, "
                                       f"{card}.querySelector('.when .age').textContent, "
                                       f"{card}.querySelector('.stale-note').textContent, "
                                       f"{card}.querySelector('.stale-note').hidden, "
                                       f"{card}.querySelector('.verdict').className, "
                                       f"{card}.querySelector('.todo').textContent]")
            local = datetime.datetime.fromtimestamp(ended, ZoneInfo(TZ))
            assert when[0] == local.strftime("%Y-%m-%d %H:%M"), when
            assert when[1] == "(3 h ago)", when
            # older than hmi.stale_after_h (2 h): flagged, in words
            assert when[3] is False and "stale: older than 2 h" in when[2], when
            assert "stale" in when[4].split()
            assert when[5].startswith("What to do: Machine fit for production"), when
            # the trend: one chart per link error and one of the volumetric distortion, each
            # on its own axis whose unit is written on it, with ± warn and fail lines
            charts = f"[...{card}.querySelectorAll('.trend svg.chart')]"
            n = await cdp.wait_for(sid, f"{charts}.length")
            got = await cdp.eval(sid, f"""{charts}.map(s => [
                s.querySelector('text.title').textContent,
                s.querySelector('text.unit').textContent,
                s.querySelectorAll('line.limit.warn').length,
                s.querySelectorAll('line.limit.fail').length,
                s.querySelectorAll('circle.pt').length])""")
            by_name = {g[0]: g[1:] for g in got}
            assert n == 9 and set(by_name) == {"EA0B", "EA0C", "EA0Y", "EB0C", "EB0Z", "EC0B",
                                              "EC0Y", "EX0C", "volumetric max"}, got
            assert {g[1] for g in got} == {"µm", "µrad"}
            assert by_name["EX0C"] == ["µm", 2, 2, 2] and by_name["EB0Z"] == ["µrad", 2, 2, 2]
            assert by_name["volumetric max"] == ["µm", 1, 1, 2]  # |distortion|: one-sided
            await cdp.screenshot(sid, tmp_path / "hmi-stale-trend.png")
    finally:
        await svc.stop()


async def test_running_row_follows_the_progress_bar_and_pdf_is_served(tmp_path):
    svc = await start_service(tmp_path, delay_s=0.02)
    try:
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.sign_in(sid, svc.hmi_url, TOKEN)
            await cdp.eval(sid, "document.querySelector('.machine .start').click(); true")
            await tick_preflight(cdp, sid)
            run_id = await cdp.wait_for(sid, "document.querySelector('#history tbody tr') && "
                                             "document.querySelector('#history tbody tr')"
                                             ".dataset.run")
            pairs = []
            snapshot = (f"[document.querySelector('.machine .state').textContent, "
                        f"document.querySelector('.machine .progress-text').textContent"
                        f".split(' touches')[0], [...document.querySelectorAll("
                        f"'#history tbody tr')].filter(r => r.dataset.run === '{run_id}')"
                        f".map(r => r.cells[5].textContent)[0]]")
            async with __import__("asyncio").timeout(60):
                while True:
                    state, bar, row = await cdp.eval(sid, snapshot)
                    if state == "CAPTURE" and row is not None:
                        pairs.append((bar, row))
                    if state == "IDLE":
                        break
            moving = {b for b, _ in pairs}
            assert len(moving) >= 5, pairs  # the bar moved while we looked
            assert all(b == r for b, r in pairs), [p for p in pairs if p[0] != p[1]][:5]
            # the finished run: its verdict is fresh, its PDF is one click away
            when = await cdp.wait_for(sid, "document.querySelector('.machine .when .age')"
                                           ".textContent")
            assert when == "(just now)"
            assert await cdp.eval(sid, "document.querySelector('.machine .stale-note').hidden")
            href = await cdp.wait_for(sid, "!document.querySelector('.machine .pdf').hidden && "
                                           "document.querySelector('.machine .pdf').href")
            assert href.endswith(f"/reports/{run_id}.pdf")
            head = await cdp.eval(sid, f"fetch('{href}').then(async r => [r.status, "
                                       "r.headers.get('content-type'), "
                                       "(await r.text()).slice(0, 5)])")
            assert head == [200, "application/pdf", "%PDF-"], head
    finally:
        await svc.stop()


async def test_phone_width_nothing_overflows(tmp_path):
    svc = await start_service(tmp_path)
    try:
        past_run(svc, "R1-older", 1, 26 * 3600)
        past_run(svc, "R2-latest", 2, 3600)
        svc.store.new_run("R3-failed", "mill1", "cnc", started_at=time.time() - 60)
        svc.store.set_state("R3-failed", "FAILED", "no probe result for 30 s after touch 17 of "
                            "140: controller silent (feed hold, alarm or lost results); "
                            "/var/lib/rumba/reports/R3-failed-with-a-long-path-name.html")
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.call("Emulation.setDeviceMetricsOverride", sid, width=390, height=844,
                           deviceScaleFactor=2, mobile=True)
            await cdp.sign_in(sid, svc.hmi_url, TOKEN)
            await cdp.wait_for(sid, "document.querySelectorAll('#history tbody tr').length == 3"
                                    " && document.querySelectorAll('svg.chart').length > 0")
            assert await cdp.eval(sid, "innerWidth") == 390
            # the cards shown (the maps card stays hidden until a map exists)
            over = await cdp.eval(sid, "[...document.querySelectorAll('.card')].filter(c => "
                                       "c.getClientRects().length).map(c => "
                                       "[c.className, c.scrollWidth, c.clientWidth])")
            assert len(over) == 2 and all(sw <= cw for _, sw, cw in over), over
            assert await cdp.eval(sid, "document.documentElement.scrollWidth") <= 390
            # every cell of a run is labelled once the table is stacked
            labels = await cdp.eval(sid, "getComputedStyle(document.querySelector("
                                         "'#history td'), '::before').content")
            assert labels == '"Started"', labels
            await cdp.screenshot(sid, tmp_path / "hmi-phone.png", whole_page=True)
    finally:
        await svc.stop()


async def test_start_refusals_are_shown_json_or_not(tmp_path):
    # a proxy in front of the daemon may answer with a text page: the operator reads it
    svc = await start_service(tmp_path, delay_s=0.05)
    try:
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.sign_in(sid, svc.hmi_url, TOKEN)
            card = "document.querySelector('.machine')"
            await cdp.eval(sid, "window.realFetch = window.fetch; window.fetch = async () => "
                                "new Response('502 Bad Gateway: upstream down', {status: 502, "
                                "headers: {'Content-Type': 'text/plain'}}); true")
            await cdp.eval(sid, f"{card}.querySelector('.start').click(); true")
            await tick_preflight(cdp, sid)
            msg = await cdp.wait_for(sid, f"{card}.querySelector('.message').textContent")
            assert msg == "502 Bad Gateway: upstream down", msg
            # an empty non-JSON answer names its status; the daemon's own refusal is JSON
            await cdp.eval(sid, "window.fetch = async () => new Response('', {status: 503}); "
                                "true")
            assert await cdp.eval(sid, "post('/x').then(r => [r.ok, r.body.error])") == \
                [False, "HTTP 503"]
            await cdp.eval(sid, "window.fetch = window.realFetch; true")
            url = f"/api/machines/{next(iter(svc.sessions))}/start"
            ticked = "{preflight: ['probe', 'balls', 'doors', 'area']}"
            first = await cdp.eval(sid, f"post('{url}', {ticked}).then(r => r.ok)")
            ok, error = await cdp.eval(sid, f"post('{url}', {ticked}).then(r => [r.ok, "
                                            "r.body.error])")
            assert first is True and ok is False and "in progress" in error, error
            await svc.sessions[next(iter(svc.sessions))].wait()
    finally:
        await svc.stop()


async def test_the_card_names_the_end_reads_not_capture(tmp_path, monkeypatch):
    """After its last touch the run waits for its end-of-run temperatures, its state still
    CAPTURE: the card says so in the daemon's one text (``phases.END_READS``) the moment the run
    gets there (published, not polled), and drops it with the next state."""
    svc = await start_service(tmp_path)
    try:
        session = next(iter(svc.sessions.values()))
        release = asyncio.Event()
        end = session.temps.end

        async def end_held(run_id: str, t_s: float) -> None:
            await release.wait()  # the reads of the end, as long as the test needs
            await end(run_id, t_s)

        monkeypatch.setattr(session.temps, "end", end_held)
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.sign_in(sid, svc.hmi_url, TOKEN)
            card = "document.querySelector('.machine')"
            seen = (f"[{card}.querySelector('.state').textContent, "
                    f"{card}.querySelector('.meaning').textContent, "
                    f"{card}.querySelector('.meaning').dataset.step]")
            await cdp.wait_for(sid, f"{card}.querySelector('.state').textContent === 'IDLE'")
            session.start("cli")
            # the end's step (the start's, START_READS, passes by first), or a run stopped
            # before it (its reason then shown at once)
            got = await cdp.wait_for(sid, f"({card}.querySelector('.meaning').dataset.step === "
                                          f"{END_READS!r} || "
                                          "['ABORTED', 'FAILED', 'INTERRUPTED'].includes("
                                          f"{card}.querySelector('.state').textContent)) && "
                                          f"{seen}")
            assert got == ["CAPTURE", END_READS, END_READS], (got, session.reason)
            release.set()
            await session.wait()
            got = await cdp.wait_for(sid, f"{card}.querySelector('.state').textContent === "
                                          f"'IDLE' && {seen}")
            assert got == ["IDLE", "ready", ""], (got, session.reason)
    finally:
        await svc.stop()


async def test_a_map_job_prompts_the_operator_and_continue_goes_on(tmp_path):
    """A machine with a map job shows Start map; between its placements the card shows the
    prompt with a Continue button, which takes the job on to the next placement."""
    from simulators.controller import VirtualController
    from simulators.frontends.opcua import OpcUaFrontend
    from tests.map_job_helpers import TOUCHES, truth, write_job

    ctrl = VirtualController(truth(0), dialect="fanuc")
    sim = OpcUaFrontend(ctrl, security="none")
    url = await sim.start()
    svc = Service(load_daemon_config(write_daemon_yaml(
        tmp_path, token=TOKEN, link=f"{{transport: opcua, url: '{url}', security: none}}",
        extra_machine=f"    map_job: {write_job(tmp_path)}")))
    await svc.start()
    try:
        session = svc.sessions["mill1"]
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.sign_in(sid, svc.hmi_url, TOKEN)
            card = "document.querySelector('.machine')"
            await cdp.wait_for(sid, f"!{card}.querySelector('.start-map').hidden")
            assert await cdp.eval(sid, f"{card}.querySelector('.prompt').hidden")
            await cdp.eval(sid, f"{card}.querySelector('.start-map').click(); true")
            await tick_preflight(cdp, sid)
            text = await cdp.wait_for(sid, f"!{card}.querySelector('.prompt').hidden && "
                                           f"{card}.querySelector('.prompt-text').textContent")
            assert text.startswith("move the artefact to placement 2 of 2 (P2)")
            assert session.job == "map" and session.done == TOUCHES
            ctrl.move_artefact(truth(1))
            await cdp.eval(sid, f"{card}.querySelector('.continue').click(); true")
            await cdp.wait_for(sid, f"{card}.querySelector('.prompt').hidden && "
                                    f"{card}.querySelector('.state').textContent === 'IDLE'",
                               timeout_s=120)
            run = svc.store.runs("mill1")[0]
            assert run.state == "DONE" and run.hits == 2 * TOUCHES, run.reason
    finally:
        await svc.stop()
        await sim.stop()
