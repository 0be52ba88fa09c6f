"""The fleet page over a real PostgreSQL: token required (bearer, login form), every machine's
last verdict with date, age and stale flag, per-link trends on separate µm and µrad axes with
their limits, drill-down to a run's report only from the allowed report directories; and the
same in headless Chromium."""

from __future__ import annotations

import asyncio
import json
import time
from contextlib import asynccontextmanager
from pathlib import Path

import aiohttp
import pytest
from aiohttp import web

from daemon.fleet import view
from daemon.fleet.app import create_fleet_app
from daemon.store.pg import PgStore, RunBatch
from tests.browser import chromium
from tests.fleet_helpers import fresh_db, start_postgres

pytestmark = [pytest.mark.peer]
TOKEN = "fleet-t0k3n-0123456789"
H = 3600.0
LIMITS = {"links": {"EAOC": {"warn": 20.0, "fail": 40.0}}, "default_um": {"warn": 10.0,
          "fail": 20.0}, "default_urad": {"warn": 30.0, "fail": 60.0}}


def analysis(eaoc_urad: float, exoc_um: float) -> str:
    return json.dumps({"machine": "m", "links": {
        "EAOC": {"value": eaoc_urad, "std": 1.0, "unit": "urad", "thesis_name": "a"},
        "EBOC": {"value": -eaoc_urad / 2, "std": 1.0, "unit": "urad", "thesis_name": "b"},
        "EXOC": {"value": exoc_um, "std": 0.5, "unit": "um", "thesis_name": "x"}}})


def run_row(run_id: str, machine: str, state: str, verdict: str | None, started: float,
            summary: str = "") -> tuple:
    return (run_id, machine, "shift", state, "", "plan.yaml", "ballbar", "fanuc", 280,
            started, started + 240, verdict, summary, 0, "")  # started_by: the CNC's shift run


async def seed(dsn: str, reports: Path, elsewhere: Path) -> dict[str, float]:
    """mill-a: PASS 1 h ago after 5 days of runs, its report in ``reports``; mill-b: FAIL
    30 h ago (stale), its report outside; mill-c: last run FAILED without a verdict."""
    store = await PgStore.connect(dsn)
    now = time.time()
    for name, dialect, transport in (("mill-a", "fanuc", "opcua"),
                                     ("mill-b", "siemens", "modbus"),
                                     ("mill-c", "heidenhain", "serial")):
        await store.write_machine((name, "plant-1", dialect, transport, json.dumps(LIMITS), now))
    for day in range(5, 0, -1):
        rid = f"A-{day}"
        started = now - day * 24 * H - 2 * H
        await store.write_run(RunBatch(run=run_row(rid, "mill-a", "DONE", "PASS", started),
                                       analysis=analysis(5.0 + day, 2.0 + day / 10)))
    last_a = now - H - 240
    (reports / "A-0.html").write_text("<html><title>report A-0</title><body>"
                                      "<h1 id='r'>Run A-0</h1></body></html>")
    await store.write_run(RunBatch(run=run_row("A-0", "mill-a", "DONE", "PASS", last_a,
                                               "all links within limits"),
                                   analysis=analysis(25.0, 3.0),
                                   report=(str(reports / "A-0.html"), str(reports / "A-0.json"))))
    (elsewhere / "B-0.html").write_text("<html>secret</html>")
    await store.write_run(RunBatch(run=run_row("B-0", "mill-b", "DONE", "FAIL", now - 30 * H),
                                   analysis=analysis(70.0, 30.0),
                                   report=(str(elsewhere / "B-0.html"), "x.json")))
    await store.write_run(RunBatch(run=run_row("C-0", "mill-c", "FAILED", None, now - 2 * H)))
    await store.close()
    return {"a_end": last_a + 240}


@pytest.fixture(scope="module")
def fleet_db(tmp_path_factory):
    pg = start_postgres()
    root = tmp_path_factory.mktemp("fleet")
    reports, elsewhere = root / "reports", root / "elsewhere"
    reports.mkdir()
    elsewhere.mkdir()
    try:
        dsn = fresh_db(pg)
        times = asyncio.run(seed(dsn, reports, elsewhere))
        yield dsn, reports, times
    finally:
        pg.close()


@asynccontextmanager
async def serving(dsn: str, reports: Path, **kw):
    app = create_fleet_app(dsn, TOKEN, reports_dirs=[reports], bind_host="127.0.0.1", **kw)
    runner = web.AppRunner(app, handle_signals=False)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    try:
        yield f"http://127.0.0.1:{runner.addresses[0][1]}"
    finally:
        await runner.cleanup()


async def test_token_required_and_checked(fleet_db):
    dsn, reports, _ = fleet_db
    async with serving(dsn, reports) as url, aiohttp.ClientSession() as http:
        async with http.get(f"{url}/api/fleet") as r:
            assert r.status == 401
        async with http.get(f"{url}/", allow_redirects=False) as r:
            assert r.status == 302 and r.headers["Location"] == "/login"
        async with http.get(f"{url}/reports/A-0.html", allow_redirects=False) as r:
            assert r.status == 302  # a report is not readable without signing in either
        async with http.get(f"{url}/api/fleet",
                            headers={"Authorization": "Bearer wrong-token-0123456789"}) as r:
            assert r.status == 401
        async with http.post(f"{url}/login", data={"token": "nope"},
                             allow_redirects=False) as r:
            assert r.status == 401
        async with http.get(f"{url}/api/fleet", headers={"Host": "evil.example"}) as r:
            assert r.status == 421  # DNS rebinding: the HMI's Host check applies here too


async def test_login_form_names_the_fleet_page(fleet_db):
    """The shared login form (daemon/hmi/login.html) names the page it signs in to."""
    dsn, reports, _ = fleet_db
    async with serving(dsn, reports) as url, aiohttp.ClientSession() as http:
        async with http.get(f"{url}/login") as r:
            page = await r.text()
        async with http.post(f"{url}/login", data={"token": "nope"}) as r:
            refused = await r.text()
    for html in (page, refused):
        assert "<p>Machine verification — fleet page</p>" in html
        assert "operator page" not in html and "{{" not in html


async def test_fleet_json_verdicts_ages_and_stale(fleet_db):
    dsn, reports, times = fleet_db
    async with serving(dsn, reports, stale_after_h=26) as url, \
            aiohttp.ClientSession(headers={"Authorization": f"Bearer {TOKEN}"}) as http, \
            http.get(f"{url}/api/fleet") as r:
        assert r.status == 200
        body = await r.json()
    got = {m["machine"]: m for m in body["machines"]}
    assert sorted(got) == ["mill-a", "mill-b", "mill-c"]
    assert got["mill-a"]["verdict"] == "PASS" and not got["mill-a"]["stale"]
    assert got["mill-a"]["run_id"] == "A-0" and got["mill-a"]["has_report"]
    assert abs(got["mill-a"]["verdict_at"] - times["a_end"]) < 1e-6
    assert 0.9 * H < got["mill-a"]["age_s"] < 1.5 * H
    assert got["mill-b"]["verdict"] == "FAIL" and got["mill-b"]["stale"]  # 30 h > 26 h
    assert got["mill-c"]["verdict"] == "ERROR" and not got["mill-c"]["stale"]
    assert (got["mill-b"]["dialect"], got["mill-b"]["transport"]) == ("siemens", "modbus")


async def test_unsafe_machine_names_are_404_not_500(fleet_db):
    dsn, reports, _ = fleet_db
    async with serving(dsn, reports) as url, \
            aiohttp.ClientSession(headers={"Authorization": f"Bearer {TOKEN}"}) as http:
        for bad in ("%00", "mill-a%00", "a%0Ab", "%E2%80%AE", "x" * 33):
            async with http.get(f"{url}/machines/{bad}") as r:
                assert r.status == 404, (bad, r.status, await r.text())
        async with http.get(f"{url}/machines/mill-a") as r:
            assert r.status == 200


def test_garbage_in_the_store_costs_a_point_never_the_page():
    """A store written by other versions or by hand: NaN and infinite numbers, limits that are
    not numbers, links that are not a mapping (each gave a 500)."""
    nan, inf = float("nan"), float("inf")
    machine = {"limits": {"links": {"EX0C": {"warn": "abc", "fail": nan}, "EB0Z": "x"},
                          "default_um": {"warn": 10, "fail": inf}, "default_urad": [1, 2]}}
    trend = [
        {"run_id": "r1", "started_at": 1.7e9, "verdict": "PASS",
         "links": {"EX0C": {"value": 5.0, "unit": "um"}, "EB0Z": {"value": nan, "unit": "urad"},
                   "EY0C": {"value": 2.0, "unit": "um"}}},
        {"run_id": "r2", "started_at": nan, "verdict": "PASS",
         "links": {"EX0C": {"value": 6.0, "unit": "um"}}},
        {"run_id": "r3", "started_at": 1.7e9 + 86400, "verdict": "WARN",
         "links": {"EX0C": {"value": "7", "unit": "um"}, "EA0B": {"value": 3.0, "unit": "urad"}}},
        {"run_id": "r4", "started_at": 1.7e9 + 2 * 86400, "verdict": "PASS", "links": "junk"},
    ]
    runs = [{"id": "r1", "started_at": nan, "trigger": "cli", "state": "DONE",
             "verdict": "PASS", "summary": "", "has_report": False}]
    page = view.machine_page("mill-x", machine, runs, trend, 90)
    assert "EX0C (1 runs)" in page and "EA0B (1 runs)" in page and "EB0Z" not in page
    # EX0C's own limits are garbage (no lines); EY0C takes default_um: warn ±10, fail inf
    assert page.count('data-limit="warn"') == 2 and 'data-limit="fail"' not in page
    assert page.index('data-limit="warn"') > page.index("EY0C (1 runs)")
    rows = view.fleet_rows([{"machine": "m", "ended_at": nan, "started_at": inf}], 1.7e9, 26)
    assert rows[0]["age_s"] is None and rows[0]["stale"]


async def test_reports_only_from_allowed_directories(fleet_db):
    dsn, reports, _ = fleet_db
    async with serving(dsn, reports) as url, \
            aiohttp.ClientSession(headers={"Authorization": f"Bearer {TOKEN}"}) as http:
        async with http.get(f"{url}/reports/A-0.html") as r:
            assert r.status == 200 and "Run A-0" in await r.text()
            assert "default-src 'none'" in r.headers["Content-Security-Policy"]
        async with http.get(f"{url}/reports/B-0.html") as r:
            text = await r.text()
            assert r.status == 404 and "secret" not in text and "B-0.html" in text
        for bad in ("..%2F..%2Fetc%2Fpasswd", "-x", "nope"):
            async with http.get(f"{url}/reports/{bad}.html") as r:
                assert r.status == 404
        async with http.get(f"{url}/machines/nope") as r:
            assert r.status == 404
        async with http.get(f"{url}/machines/mill-a?days=0") as r:
            assert r.status == 400


async def test_store_down_is_503_not_a_traceback(tmp_path):
    dsn = "postgresql://rumba@127.0.0.1:1/none?connect_timeout=1"
    async with serving(dsn, tmp_path) as url, \
            aiohttp.ClientSession(headers={"Authorization": f"Bearer {TOKEN}"}) as http, \
            http.get(f"{url}/api/fleet") as r:
        assert r.status == 503 and "unreachable" in await r.text()


async def test_fleet_page_in_chromium(fleet_db, tmp_path):
    dsn, reports, _ = fleet_db
    async with serving(dsn, reports, stale_after_h=26) as url, \
            chromium(tmp_path / "profile") as cdp:
        sid = await cdp.page()
        await cdp.sign_in_fleet(sid, url + "/", TOKEN)
        rows = await cdp.eval(sid, """[...document.querySelectorAll('tr.row')].map(r => [
            r.dataset.machine, r.querySelector('.badge')?.textContent,
            r.querySelector('.age').textContent, !!r.querySelector('.stale-flag'),
            r.querySelector('.date').textContent])""")
        by = {r[0]: r for r in rows}
        assert by["mill-a"][1] == "PASS" and by["mill-a"][2].startswith("1 h ")
        assert not by["mill-a"][3] and by["mill-b"][3], rows
        # mill-b's run ended 240 s after its start, 30 h ago
        assert by["mill-b"][1] == "FAIL" and by["mill-b"][2].startswith("29 h 5")
        assert by["mill-c"][1] == "ERROR"
        assert by["mill-a"][4][:4].isdigit()  # a date, not "—"
        # drill-down: machine page with the trend on two unit axes
        await cdp.eval(sid, "document.querySelector('tr[data-machine=\"mill-a\"] "
                            "a.machine-link').click(); true")
        await cdp.wait_for(sid, "location.pathname === '/machines/mill-a' && "
                                "document.querySelectorAll('svg.chart').length > 0")
        charts = await cdp.eval(sid, """[...document.querySelectorAll('svg.chart')].map(s => [
            s.dataset.link, s.dataset.unit, s.querySelector('.axis-label').textContent,
            s.querySelectorAll('line.limit.warn').length,
            s.querySelectorAll('line.limit.fail').length, s.querySelectorAll('circle').length,
            s.getBoundingClientRect().height > 50])""")
        assert sorted(c[0] for c in charts) == ["EAOC", "EBOC", "EXOC"]
        units = {c[0]: c[1] for c in charts}
        assert units == {"EAOC": "µrad", "EBOC": "µrad", "EXOC": "µm"}
        assert all(c[1] == c[2] for c in charts)  # each axis labelled with its own unit
        assert all(c[3] == 2 and c[4] == 2 and c[5] == 6 and c[6] for c in charts), charts
        # the report link of the last run opens the report the daemon wrote
        await cdp.eval(sid, "document.querySelector('table.runs a.report').click(); true")
        await cdp.wait_for(sid, "document.getElementById('r')?.textContent === 'Run A-0'")


def test_fleet_command_refuses_bad_arguments(tmp_path, capsys):
    from daemon.cli.main import main

    token = tmp_path / "t"
    token.write_text(TOKEN)
    token.chmod(0o644)
    cases = [(["--store", "sqlite:///x.sqlite", "--token-file", str(token)], "PostgreSQL"),
             (["--store", "postgresql://r@h/d", "--token-file", str(token),
               "--listen", "nope"], "--listen: expected HOST:PORT"),
             (["--store", "postgresql://r@h/d", "--token-file", str(token)],
              "readable by others")]
    for args, why in cases:
        assert main(["fleet", *args]) == 2
        assert why in capsys.readouterr().err


async def test_fleet_command_serves_the_store(fleet_db, tmp_path):
    import sys

    dsn, reports, _ = fleet_db
    token = tmp_path / "t"
    token.write_text(TOKEN)
    token.chmod(0o600)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "daemon.cli", "fleet", "--store", dsn, "--token-file", str(token),
        "--listen", "127.0.0.1:0", "--reports-dir", str(reports),
        stdout=asyncio.subprocess.PIPE)
    try:
        line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
        assert line.startswith("rumba fleet: http://127.0.0.1:"), line
        url = line.split(": ", 1)[1].strip()
        async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {TOKEN}"}) as h, \
                h.get(url + "api/fleet") as r:
            assert r.status == 200 and len((await r.json())["machines"]) == 3
    finally:
        proc.terminate()
        assert await asyncio.wait_for(proc.wait(), 30) == 0  # SIGTERM: a clean stop


def test_run_list_names_the_drift_baseline_and_a_report_being_written():
    """Each run says which baseline its drift was judged against (the verdict's
    drift checks) or that there was none; a run whose report is still being written (after
    the run's end) or failed says so instead of a bare "—"."""
    import re

    def run(i: str, **kw):
        return {"id": i, "started_at": 1.7e9, "trigger": "cli", "state": "DONE",
                "verdict": "PASS", "summary": "", "has_report": False, **kw}

    checks = [{"quantity": "EX0C", "reference_run": None},
              {"quantity": "EX0C drift", "reference_run": "R7", "reference": 1.0}]
    runs = [run("a", checks=json.dumps(checks), reasons="[]", has_report=True),
            run("b", checks="[]", reasons=json.dumps(["drift not checked: no baseline"]),
                report_state="writing"),
            # the report job's own row (migration 10), not the run's reason, says why
            run("c", checks="[]", reasons="[]", reason="", report_state="failed",
                report_error="OSError: disk full"),
            run("d", checks="not json", reasons=None, state="CAPTURE", verdict=None),
            run("e", checks="[]", reasons="[]", reason="report not written: in the reason")]
    page = view.machine_page("mill-x", None, runs, [], 90)
    assert "<th>Drift baseline</th>" in page
    cells = re.findall(r'<td class="baseline">([^<]*)</td><td>(.*?)</td></tr>', page)
    assert cells[0] == ("run R7", '<a class="report" href="/reports/a.html">report</a>')
    assert cells[1] == ("drift not checked: no baseline",
                        '<span class="report-writing">report being written</span>')
    assert cells[2][1] == ('<span class="report-failed">report not written: OSError: disk '
                           'full</span>')
    assert cells[3] == ("—", "—")
    assert cells[4] == ("—", "—")  # a DONE run without a report job: nothing to tell of
