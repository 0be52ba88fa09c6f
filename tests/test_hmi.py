"""The HMI over real HTTP on a free loopback port: auth (bearer, login cookie), CSRF, start /
refuse / abort, live progress over SSE, reports; and in headless Chromium (peer)."""

from __future__ import annotations

import asyncio
import json
import time

import aiohttp
import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from contracts.yaml_files import ConfigError
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.service.service import Service
from tests.browser import chromium, tick_preflight

TOKEN = "t0k3n-for-tests-0123456789"


@pytest.fixture
async def service(tmp_path):
    cfg = load_daemon_config(write_daemon_yaml(tmp_path, token=TOKEN))
    setup = thesis_setup()
    rows = thesis_rows(setup)
    links: list[ReplayLink] = []

    def factory(s):
        links.append(ReplayLink(rows, s.machine, delay_s=0.01))
        return links[-1]

    svc = Service(cfg, factory, prepare=prepare_from_rows(rows))
    await svc.start()
    svc.test_links = links  # type: ignore[attr-defined]
    yield svc
    await svc.stop()


@pytest.fixture
async def sim_service(tmp_path):
    """The service against the simulated CNC over OPC UA (real asyncua server and driver)."""
    from benchmarks.rigs.daemon_helpers import CONFIG
    from simulators.controller import VirtualController
    from simulators.frontends.opcua import OpcUaFrontend
    from simulators.truth import TruthModel

    truth = TruthModel.from_files(CONFIG / "machines/thesis_wcbxfzyt.yaml",
                                  CONFIG / "artefacts/thesis_4ball.yaml",
                                  CONFIG / "errors/thesis_tableB2.yaml")
    ctrl = VirtualController(truth, time_scale=0.03, dialect="fanuc")
    sim = OpcUaFrontend(ctrl, security="none")
    url = await sim.start()
    cfg = load_daemon_config(write_daemon_yaml(
        tmp_path, token=TOKEN, link=f"{{transport: opcua, url: '{url}', security: none}}"))
    svc = Service(cfg)
    await svc.start()
    yield svc
    await svc.stop()
    await sim.stop()


def bearer(token: str = TOKEN) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


async def test_binds_loopback_and_requires_a_token(service):
    assert service.hmi_url.startswith("http://127.0.0.1:")
    async with aiohttp.ClientSession() as http:
        r = await http.get(service.hmi_url + "api/status")
        assert r.status == 401
        r = await http.get(service.hmi_url + "api/status", headers=bearer("x" * 26))
        assert r.status == 401
        r = await http.post(service.hmi_url + "api/machines/mill1/start",
                            headers=bearer(TOKEN[:-1] + "X"))
        assert r.status == 401
        r = await http.get(service.hmi_url, allow_redirects=False)
        assert r.status == 302 and r.headers["Location"] == "/login"
        r = await http.get(service.hmi_url + "api/status", headers=bearer())
        assert r.status == 200 and (await r.json())["mill1"]["state"] == "IDLE"


async def test_login_form_names_the_operator_page(service):
    """The shared login form (login.html) names the page it signs in to: the HMI's here."""
    async with aiohttp.ClientSession() as http:
        page = await (await http.get(service.hmi_url + "login")).text()
        refused = await (await http.post(service.hmi_url + "login", data={"token": "x"})).text()
    for html in (page, refused):
        assert "<p>Machine verification — operator page</p>" in html
        assert "fleet page" not in html and "{{" not in html


async def test_login_cookie_csrf_and_origin(service):
    jar = aiohttp.CookieJar(unsafe=True)
    async with aiohttp.ClientSession(cookie_jar=jar) as http:
        r = await http.post(service.hmi_url + "login", data={"token": "wrong"})
        assert r.status == 401 and "Wrong token" in await r.text()
        r = await http.post(service.hmi_url + "login", data={"token": TOKEN},
                            allow_redirects=False)
        assert r.status == 303
        cookie = r.headers["Set-Cookie"]
        assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
        page = await (await http.get(service.hmi_url)).text()
        csrf = page.split('name="csrf-token" content="')[1].split('"')[0]
        assert len(csrf) > 20
        url = service.hmi_url + "api/machines/mill1/start"
        assert (await http.post(url)).status == 403  # cookie alone: no CSRF token
        r = await http.post(url, headers={"X-CSRF-Token": csrf, "Origin": "http://evil.example"})
        assert r.status == 403
        r = await http.post(url, headers={"X-CSRF-Token": csrf})  # no pre-flight
        assert r.status == 400 and "pre-flight checklist not confirmed" in await r.text()
        r = await http.post(url, headers={"X-CSRF-Token": csrf},
                            json={"preflight": ["probe", "balls", "doors"]})  # one unticked
        assert r.status == 400 and "Working area clear" in await r.text()
        preflight = {"preflight": ["probe", "balls", "doors", "area"]}
        r = await http.post(url, headers={"X-CSRF-Token": csrf}, json=preflight)
        assert r.status == 202
        run_id = (await r.json())["run_id"]
        r = await http.post(url, headers={"X-CSRF-Token": csrf}, json=preflight)
        assert r.status == 409 and run_id in (await r.json())["error"]
        r = await http.post(service.hmi_url + "api/machines/mill1/abort",
                            headers={"X-CSRF-Token": csrf})
        assert r.status == 200 and (await r.json())["reason"].startswith("aborted by hmi during ")


async def test_sse_progress_verdict_and_report(service):
    async with aiohttp.ClientSession(headers=bearer()) as http:
        events = await http.get(service.hmi_url + "api/events")
        assert events.headers["Content-Type"].startswith("text/event-stream")
        r = await http.post(service.hmi_url + "api/machines/mill1/start")
        run_id = (await r.json())["run_id"]
        seen_done, states, ends = [], [], []
        async with asyncio.timeout(60):
            async for line in events.content:
                if line.startswith(b"data: "):
                    st = json.loads(line[6:])
                    seen_done.append(st["done"])
                    states.append(st["state"])
                    if st["state"] == "IDLE" and st["run_id"] == run_id:
                        # the run's end first, then its report (written after it)
                        ends.append(st["verdict"]["report_state"])
                        if ends[-1] != "writing":
                            break
        events.close()
        assert ends[0] == "writing" and ends[-1] == "written", ends
        assert "CAPTURE" in states and "IDENTIFY" in states
        progress = [d for d in seen_done if 0 < d < 140]
        assert len(progress) > 10 and progress == sorted(progress)
        assert st["verdict"]["status"] == "PASS"
        r = await http.get(service.hmi_url + f"reports/{run_id}.html")
        assert r.status == 200 and run_id in await r.text()
        assert "default-src 'none'" in r.headers["Content-Security-Policy"]
        doc = await (await http.get(service.hmi_url + f"reports/{run_id}.json")).json()
        assert doc["verdict"]["status"] == "PASS" and "EX0C" in doc["analysis"]["links"]
        runs = await (await http.get(service.hmi_url + "api/runs")).json()
        assert runs[0]["id"] == run_id and runs[0]["report"] == f"/reports/{run_id}.html"
        for bad in ("nope", "..%2F..%2Fetc%2Fpasswd"):
            assert (await http.get(service.hmi_url + f"reports/{bad}.html")).status == 404
    assert service.test_links[0].verdicts[-1].status == "PASS"


# ------------------------------------------------------------------------ headless browser


@pytest.mark.peer
@pytest.mark.slow
async def test_browser_start_progress_verdict_report(sim_service, tmp_path):
    """Chromium, driven over the DevTools protocol: sign in, press Start, watch the progress
    advance while the simulated CNC probes over OPC UA, see the verdict and the run's row in
    the history table arrive live (no reload), open the report."""
    service = sim_service
    # An older run, so the history table has a row at page load.
    service.store.new_run("20200101T000000Z-0a0a", "mill1", "import", state="IMPORTED",
                          imported=True, started_at=time.time() - 86400)
    async with chromium(tmp_path / "profile") as cdp:
        sid = await cdp.page()
        await cdp.sign_in(sid, service.hmi_url, TOKEN)
        assert await cdp.eval(sid, "document.querySelector('.machine .state').textContent"
                              ) == "IDLE"
        rows = "[...document.querySelectorAll('#history tbody tr')]"
        await cdp.wait_for(sid, f"{rows}.length > 0")
        assert await cdp.eval(sid, f"{rows}.map(r => r.dataset.run)") == [
            "20200101T000000Z-0a0a"]
        # A mark on this document: still there at the end = no navigation, no reload.
        await cdp.eval(sid, "window.rumbaNoReload = 1; true")
        await cdp.eval(sid, "document.querySelector('.machine .start').click(); true")
        await tick_preflight(cdp, sid)
        progress = set()
        async with asyncio.timeout(60):
            while True:
                st = await cdp.eval(sid, "[document.querySelector('.machine .state')"
                                         ".textContent, document.querySelector("
                                         "'.machine .progress-text').textContent]")
                if st[0] == "CAPTURE":
                    progress.add(st[1])
                    if len(progress) == 5:
                        await cdp.screenshot(sid, tmp_path / "hmi-running.png")
                if st[0] == "IDLE" and progress:
                    break
                await asyncio.sleep(0.03)
        assert len(progress) >= 3, progress  # the progress text advanced while running
        assert any("touches" in p and "left" in p for p in progress)
        badge = await cdp.wait_for(sid, "document.querySelector('.machine .badge')"
                                        ".textContent.replace('none yet', '')")
        assert badge == "PASS"
        assert await cdp.eval(sid, "getComputedStyle(document.querySelector("
                                   "'.machine .badge')).backgroundColor"
                              ) == "rgb(27, 135, 63)"
        run_id = service.sessions["mill1"].run_id
        assert run_id and run_id != "20200101T000000Z-0a0a"
        # The new run's row arrives in the open page once the run has ended (DONE, PASS).
        row = (f"{rows}.filter(r => r.dataset.run === '{run_id}')"
               ".map(r => [...r.cells].map(c => c.textContent))[0]")
        cells = await cdp.wait_for(sid, f"(({row}) || [])[3] === 'DONE' && ({row})", 10)
        assert cells[1:5] == ["mill1", "hmi", "DONE", "PASS"], cells
        assert await cdp.eval(sid, f"{rows}.map(r => r.dataset.run)") == [
            run_id, "20200101T000000Z-0a0a"]
        assert await cdp.eval(sid, "window.rumbaNoReload") == 1
        await cdp.screenshot(sid, tmp_path / "hmi-done.png")
        # the card's link appears once the report is written (after the run's end)
        href = await cdp.wait_for(sid, "!document.querySelector('.machine .report').hidden && "
                                       "document.querySelector('.machine .report').href")
        assert href.endswith(".html")
        assert await cdp.eval(sid, "document.querySelector('.machine .report-state').hidden")
        await cdp.call("Page.navigate", sid, url=href)
        await cdp.wait_for(sid, "document.readyState === 'complete' && "
                                "document.title.startsWith('rumba run')")
        assert await cdp.eval(sid, "document.querySelector('.badge').textContent") == "PASS"
        n_img = await cdp.eval(sid, "[...document.images].filter(i => i.naturalWidth > 0)"
                                    ".length")
        assert n_img >= 3  # embedded plots decoded


async def test_service_serves_with_the_hmi_limits(service):
    """The daemon's own runner gets the header timeout and sizes (``handler_args`` of the app),
    not aiohttp's defaults (a one-hour keep-alive held half-sent headers that long)."""
    from daemon.hmi.limits import HmiLimits

    kwargs = service._runner.server._kwargs  # what every connection's RequestHandler gets
    limits = HmiLimits()
    assert kwargs["keepalive_timeout"] == limits.header_timeout_s
    assert kwargs["max_line_size"] == limits.max_line_bytes
    assert kwargs["lingering_time"] == limits.linger_s
    assert service._runner.app._client_max_size == limits.max_body_bytes


async def test_public_origins_from_daemon_yaml(tmp_path):
    """``hmi.public_origins`` reaches the service: that DNS name is served, others get 421."""
    path = write_daemon_yaml(tmp_path, token=TOKEN)
    path.write_text(path.read_text().replace(
        f"token: {TOKEN}}}",
        f"token: {TOKEN}, public_origins: ['http://rumba.plant.example:8470']}}"))
    setup = thesis_setup()
    rows = thesis_rows(setup)
    svc = Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        async with aiohttp.ClientSession() as http:
            for host, status in (("rumba.plant.example:8470", 200), ("evil.example:8470", 421)):
                r = await http.get(svc.hmi_url + "api/status", headers={**bearer(), "Host": host})
                assert r.status == status, host
    finally:
        await svc.stop()


def test_bad_public_origin_is_one_line(tmp_path):
    path = write_daemon_yaml(tmp_path, token=TOKEN)
    path.write_text(path.read_text().replace(
        f"token: {TOKEN}}}", f"token: {TOKEN}, public_origins: ['rumba.local/x']}}"))
    with pytest.raises(ConfigError, match=r"hmi.public_origins: .*expected http\(s\)://host"):
        load_daemon_config(path)


@pytest.mark.peer
async def test_a_report_jobs_end_shows_in_the_history_and_on_the_card(service, tmp_path):
    """The report job's own record (migration 10), not the run's reason: a journaled run whose
    report failed says why in its history row and on its machine's card (the daemon has no
    live verdict yet); one still being written says so."""
    from daemon.store import report_jobs

    store, now = service.store, time.time()
    for rid, status, ago in (("20200101T000000Z-0a0a", "FAIL", 7200),
                             ("20200101T000000Z-0b0b", "WARN", 3600)):
        store.new_run(rid, "mill1", "cnc", state="WRITE-BACK", started_at=now - ago)
        store.save_verdict(rid, status, ["r"], [], status)
        report_jobs.begin(store, rid)
        store.set_state(rid, "DONE")
    report_jobs.failed(store, "20200101T000000Z-0a0a", "OSError: [Errno 28] disk full")
    async with chromium(tmp_path / "profile") as cdp:
        sid = await cdp.page()
        await cdp.sign_in(sid, service.hmi_url, TOKEN)
        rows = "[...document.querySelectorAll('#history tbody tr')]"
        cells = await cdp.wait_for(sid, f"{rows}.length === 2 && {rows}.map(r => "
                                        "[r.dataset.run, r.cells[6].textContent, "
                                        "r.cells[7].textContent])")
        assert cells == [
            ["20200101T000000Z-0b0b", "WARN", "report being written…"],
            ["20200101T000000Z-0a0a", "FAIL", "report not written: OSError: [Errno 28] disk "
                                              "full"]], cells
        # the card shows the last journaled verdict (WARN) with its report job's state
        card = await cdp.wait_for(sid, "document.querySelector('.machine .badge').textContent"
                                       " === 'WARN' && document.querySelector("
                                       "'.machine .report-state').textContent")
        assert card == "report being written…"
