"""Temperature channels in the fleet store, against a real PostgreSQL started by the test: each
run's raw temperature readings are drained with its rows (journal order, nothing lost or copied
twice, readings journaled before their trigger existed queued with their run), and the fleet
page fits a link error against a channel over the runs with the statistics of ``rumba history
--against-temperature`` (r, slope ± u, 95 % Student's t interval) — checked against numpy /
scipy here, and in headless Chromium."""

from __future__ import annotations

import asyncio
import json
import math
import time

import aiohttp
import numpy as np
import psycopg
import pytest
from scipy import stats

from benchmarks.rigs.temperature_helpers import fleet_against
from contracts.temperatures import TemperatureReading
from daemon.analysis.temperature_trend import TempPoint, fit
from daemon.store.drain import Drainer
from daemon.store.journal import Store
from daemon.store.pg import RUN_COLS, PgStore, RunBatch
from daemon.store.pg_temperatures import TEMP_COLS
from daemon.store.temperatures import journal_temperature
from tests.browser import chromium
from tests.fleet_helpers import fresh_db, pg
from tests.test_fleet_page import TOKEN, serving

__all__ = ["pg"]  # the module's PostgreSQL (tests/fleet_helpers.py)
pytestmark = [pytest.mark.peer]
DAY = 86400.0


def pg_rows(dsn: str, run_id: str) -> list[tuple]:
    with psycopg.connect(dsn) as c:
        return c.execute(f"SELECT {', '.join(TEMP_COLS)} FROM temperatures WHERE run_id=%s"
                         " ORDER BY seq", (run_id,)).fetchall()


def local_rows(store: Store, run_id: str) -> list[tuple]:
    return store.db.execute(f"SELECT {', '.join(TEMP_COLS)} FROM temperatures WHERE run_id=?"
                            " ORDER BY seq", (run_id,)).fetchall()


async def test_raw_readings_reach_the_fleet_store_once_each(pg, tmp_path):
    dsn = fresh_db(pg)
    store = Store(tmp_path / "journal.sqlite")
    # a run journaled by an older daemon during an outage: its run row waits in the outbox
    # (the old triggers queued it), its readings were journaled without a trigger
    store.new_run("20260101-000000-old1", "mill1", "cnc")
    store.db.execute("INSERT INTO outbox(kind, key) VALUES ('runs', '20260101-000000-old1')")
    for i in range(3):
        journal_temperature(store, "20260101-000000-old1", TemperatureReading(
            "spindle", "pose", i, 10.0 * i, 21.0 + i))
    drainer = Drainer(store, dsn)
    try:
        queued = store.db.execute("SELECT COUNT(*) FROM outbox WHERE kind='temperatures'"
                                  ).fetchone()[0]
        assert queued == 3
        Drainer(store, dsn)  # a second start queues nothing twice
        assert store.db.execute("SELECT COUNT(*) FROM outbox WHERE kind='temperatures'"
                                ).fetchone()[0] == 3
        run = "20260102-060000-new1"
        store.new_run(run, "mill1", "cnc")
        readings = [TemperatureReading("spindle", "start", None, 0.0, 20.512),
                    TemperatureReading("column", "start", None, 0.0, None,
                                       "no answer in 3 s; not read again until the end"),
                    *[TemperatureReading("spindle", "pose", p, 30.0 * p, 20.6 + 0.1 * p)
                      for p in range(4)]]
        for r in readings:
            journal_temperature(store, run, r)
        await drainer.drain()
        assert pg_rows(dsn, run) == local_rows(store, run)  # every column, journal order
        assert pg_rows(dsn, "20260101-000000-old1") == local_rows(store,
                                                                 "20260101-000000-old1")
        got = pg_rows(dsn, run)
        assert got[1][6] is None and "no answer" in got[1][7]  # the unread one, with why
        journal_temperature(store, run, TemperatureReading("spindle", "end", None, 150.0,
                                                           21.2))
        await drainer.drain()
        await drainer.drain()
        assert len(pg_rows(dsn, run)) == len(readings) + 1 == len(local_rows(store, run))
        # a batch copied again after a lost acknowledgement leaves one row each
        again = await PgStore.connect(dsn)
        try:
            await again.write_run(RunBatch(
                run=store.db.execute(f"SELECT {', '.join(RUN_COLS)} FROM runs WHERE id=?",
                                     (run,)).fetchone(),
                temperatures=local_rows(store, run)))
        finally:
            await again.close()
        assert pg_rows(dsn, run) == local_rows(store, run)
        assert drainer.backlog() == 0
    finally:
        await drainer.stop()
        store.close()


# ---------------------------------------------------------------- link against temperature
SLOPE_UM_PER_C = 1.5  # EX0C grows with the spindle temperature (what a shop wants to see)


def run_row(run_id: str, started: float) -> tuple:
    values = {"id": run_id, "machine": "mill-t", "trigger": "cnc", "state": "DONE",
              "reason": "", "plan": "p", "artefact": "a", "dialect": "fanuc",
              "touch_total": 140, "started_at": started, "ended_at": started + 200,
              "verdict": "PASS", "summary": "", "imported": 0, "started_by": ""}
    return tuple(values[c] for c in RUN_COLS)


def planted() -> list[dict]:
    """Nine runs: spindle readings per pose, EX0C = 4 + 1.5·(T − 22) + scatter, EA0B flat;
    run 7 has only start and end readings, run 8 has its spindle unread (no point)."""
    rng = np.random.default_rng(22)
    out = []
    for k in range(9):
        base = 19.0 + 0.8 * k + rng.normal(0, 0.3)
        pose = [] if k == 7 else [base + 0.2 * p for p in range(5)]
        start, end = base - 0.1, base + 1.1
        mean = (sum(pose) / len(pose)) if pose else (start + end) / 2
        ex = 4.0 + SLOPE_UM_PER_C * (mean - 22.0) + rng.normal(0, 0.4)
        out.append({"id": f"R-{k}", "pose": pose, "start": start, "end": end, "mean": mean,
                    "ex": ex, "ex_std": 0.35 + 0.01 * k, "ea": 3.0 + rng.normal(0, 2.0),
                    "unread": k == 8})
    return out


async def seed(dsn: str, runs: list[dict]) -> None:
    store = await PgStore.connect(dsn)
    now = time.time()
    try:
        for k, r in enumerate(runs):
            read = [("start", None, r["start"]), *[("pose", p, v) for p, v in
                                                   enumerate(r["pose"])], ("end", None, r["end"])]
            rows = [(r["id"], seq, "spindle", at, pose, 10.0 * seq,
                     None if r["unread"] else value, "not read" if r["unread"] else "", now,
                     0)  # TEMP_COLS: the plan's program (no re-probe round)
                    for seq, (at, pose, value) in enumerate(read, 1)]
            links = {"EX0C": {"value": r["ex"], "std": r["ex_std"], "unit": "um"},
                     "EA0B": {"value": r["ea"], "std": 1.0, "unit": "urad"}}
            temps = {"spindle": {"source": "spindle: opcua /T", "start_c": r["start"],
                                 "end_c": r["end"]}}
            await store.write_run(RunBatch(
                run=run_row(r["id"], now - (10 - k) * DAY),
                analysis=json.dumps({"machine": "mill-t", "links": links,
                                     "temperatures": temps}), temperatures=rows))
    finally:
        await store.close()


def expected(runs: list[dict]) -> dict:
    """The fit, computed independently of the product (numpy, scipy)."""
    used = [r for r in runs if not r["unread"]]
    t = np.array([r["mean"] for r in used])
    v = np.array([r["ex"] for r in used])
    slope, intercept = np.polyfit(t, v, 1)
    res = v - (intercept + slope * t)
    u = math.sqrt(float(res @ res) / (len(t) - 2) / float(((t - t.mean()) ** 2).sum()))
    return {"n": len(used), "r": float(np.corrcoef(t, v)[0, 1]), "slope": float(slope),
            "slope_std": u, "slope_u95": float(stats.t.ppf(0.975, len(t) - 2)) * u,
            "temps": {r["id"]: r["mean"] for r in used}}


@pytest.fixture(scope="module")
def against_db(pg):
    dsn = fresh_db(pg)
    runs = planted()
    asyncio.run(seed(dsn, runs))
    return dsn, runs


async def test_link_against_temperature_has_the_cli_statistics(against_db, tmp_path):
    dsn, runs = against_db
    want = expected(runs)
    async with serving(dsn, tmp_path) as url, aiohttp.ClientSession(
            headers={"Authorization": f"Bearer {TOKEN}"}) as http:
        got = await fleet_against(http, url, "mill-t")
        async with http.get(f"{url}/machines/mill-t/temperature") as r:
            default = await r.text()  # the first channel and link (sorted)
        async with http.get(f"{url}/machines/mill-t/temperature",
                            params={"link": "EX0C"}) as r:
            page = await r.text()
            assert r.status == 200, page
        async with http.get(f"{url}/machines/mill-t") as r:
            machine_page = await r.text()
        bad = {}
        for q in ({"channel": "spindel"}, {"link": "EX9Q"}, {"link": "EX0C;M30"},
                  {"channel": "a/b"}):
            async with http.get(f"{url}/machines/mill-t/temperature", params=q) as r:
                bad[json.dumps(q)] = (r.status, await r.text())
        async with http.get(f"{url}/machines/mill-x/temperature") as r:
            bad["mill-x"] = (r.status, await r.text())
    assert got["n"] == want["n"] == 8 and got["unit"] == "µm" and got["slope_unit"] == "µm/°C"
    for k in ("r", "slope", "slope_std", "slope_u95"):
        assert got[k] == pytest.approx(want[k], rel=1e-9), k
    assert abs(got["slope"] - SLOPE_UM_PER_C) < 3 * got["slope_std"]  # finds what was planted
    assert {p["run_id"]: p["temperature_c"] for p in got["points"]} == pytest.approx(
        want["temps"])  # run 7 from its start and end, run 8 (unread) left out
    # the same function as rumba history --against-temperature: its text, word for word
    pts = [TempPoint(p["run_id"], p["temperature_c"], p["value"], p["std"])
           for p in got["points"]]
    assert got["text"] == fit(pts, "µm").text("EX0C", "spindle")
    assert 'data-link="EA0B" data-channel="spindle"' in default
    # the page: the figures, one point per run
    assert f'<dd class="r">{want["r"]:+.2f}</dd>' in page
    assert f'{want["slope"]:+.3g} ± {want["slope_std"]:.3g} µm/°C' in page
    assert f'± {want["slope_u95"]:.3g} µm/°C' in page and "(Student's t, 6 dof)" in page
    assert page.count('<circle class="pt"') == 8 and 'class="fit"' in page
    assert "not in the fit (no value)" in page and "0 of 7" in page  # run 8's row says why
    assert 'href="/machines/mill-t/temperature"' in machine_page
    assert bad['{"channel": "spindel"}'][0] == 404 and "channels: spindle" in \
        bad['{"channel": "spindel"}'][1]
    assert bad['{"link": "EX9Q"}'][0] == 404 and "links: EA0B, EX0C" in bad['{"link": "EX9Q"}'][1]
    assert bad['{"link": "EX0C;M30"}'][0] == 400 and bad['{"channel": "a/b"}'][0] == 400
    assert bad["mill-x"][0] == 404 and "no temperature readings" in bad["mill-x"][1]


async def test_link_against_temperature_in_chromium(against_db, tmp_path):
    dsn, runs = against_db
    want = expected(runs)
    async with serving(dsn, tmp_path) as url, chromium(tmp_path / "profile") as cdp:
        sid = await cdp.page()
        await cdp.sign_in_fleet(sid, url + "/machines/mill-t", TOKEN)
        await cdp.call("Page.navigate", sid, url=url + "/machines/mill-t")
        await cdp.wait_for(sid, "location.pathname === '/machines/mill-t' && "
                                "document.readyState === 'complete'")
        assert await cdp.eval(sid, "!!document.querySelector('a.against-temperature')")
        await cdp.eval(sid, "document.querySelector('a.against-temperature').click(); true")
        await cdp.wait_for(sid, "document.querySelector('svg.scatter')?.dataset.link === "
                                "'EA0B'")  # the first link: a rotation, in µrad
        slope = await cdp.eval(sid, "document.querySelector('dd.slope').textContent")
        assert slope.endswith("µrad/°C"), slope
        # another link from the form
        await cdp.eval(sid, "document.getElementById('link').value = 'EX0C';"
                            "document.querySelector('form.against').submit(); true")
        await cdp.wait_for(sid, "document.querySelector('svg.scatter')?.dataset.link === "
                                "'EX0C'")
        seen = await cdp.eval(sid, """({
            link: document.querySelector('svg.scatter').dataset.link,
            points: document.querySelectorAll('svg.scatter circle.pt').length,
            r: document.querySelector('dd.r').textContent,
            n: document.querySelector('dd.n').textContent,
            fit: !!document.querySelector('svg.scatter line.fit'),
            height: document.querySelector('svg.scatter').getBoundingClientRect().height})""")
        assert seen == {"link": "EX0C", "points": 8, "r": f"{want['r']:+.2f}", "n": "8",
                        "fit": True, "height": 320}, seen
