"""A stored analysis holding NaN or Infinity (an older version's, or one written by hand) costs
its cells on the fleet page, never the page: PostgreSQL's jsonb refuses those numbers, and the
machine page, its trend and its link-against-temperature view answered 500."""

from __future__ import annotations

import json
import time

import aiohttp
import pytest

from daemon.store.pg import PgStore, RunBatch
from tests.fleet_helpers import fresh_db, start_postgres
from tests.test_fleet_page import TOKEN, serving
from tests.test_temperature_fleet import row

pytestmark = [pytest.mark.peer]
NAN, INF = float("nan"), float("inf")


def bad_analysis(k: int) -> str:
    return json.dumps({
        "machine": "m",
        "links": {"EX0C": {"value": NAN, "std": INF, "unit": "um", "thesis_name": "x"},
                  "EB0C": {"value": 5.0 + k, "std": NAN, "unit": "urad", "thesis_name": "b"}},
        "temperatures": {"spindle": {"source": "spindle: opcua /T", "start_c": NAN,
                                     "end_c": -INF, "change_c": 1.5}},
        "estimation": {"index_scatter": {"C": {"run_urad": NAN, "stated_urad": 3.0}}},
        "warnings": ["u of EX0C not finite"]})  # json.dumps writes NaN / Infinity


async def test_a_stored_nan_never_makes_the_fleet_page_fail(tmp_path):
    pg = start_postgres()
    try:
        dsn = fresh_db(pg)
        store = await PgStore.connect(dsn)
        now = time.time()
        for k in range(3):
            rid = f"N-{k}"
            temps = [(rid, 1, "spindle", "start", None, 0.0, 20.0 + k, "", now, 0),
                     (rid, 2, "spindle", "pose", 0, 10.0, NAN, "", now, 0),
                     (rid, 3, "spindle", "end", None, 200.0, 22.0 + k, "", now, 0)]
            await store.write_run(RunBatch(run=row(rid, now - 3600 * (3 - k)),
                                           analysis=bad_analysis(k), temperatures=temps))
        runs = await store.runs("mill-t", 10)
        trend = await store.trend("mill-t", now - 86400)
        await store.close()
        assert [r["id"] for r in runs] == ["N-2", "N-1", "N-0"]
        assert runs[0]["temperatures"]["spindle"] == {
            "source": "spindle: opcua /T", "start_c": None, "end_c": None, "change_c": 1.5}
        assert runs[0]["index_scatter"]["index_scatter"] == {
            "C": {"run_urad": None, "stated_urad": 3.0}}
        assert trend[0]["links"]["EX0C"]["value"] is None
        assert trend[2]["links"]["EB0C"]["value"] == 7.0
        async with serving(dsn, tmp_path) as url, aiohttp.ClientSession(
                headers={"Authorization": f"Bearer {TOKEN}"}) as http:
            for path in ("/machines/mill-t", "/api/fleet", "/machines/mill-t/temperature",
                         "/machines/mill-t/temperature?link=EB0C",
                         "/api/machines/mill-t/temperature?link=EB0C"):
                async with http.get(f"{url}{path}") as r:
                    body = await r.text()
                    assert r.status == 200, (path, body[:500])
                    if path.startswith("/api/"):  # JSON a browser parses: no NaN token
                        assert not [t for t in ("NaN", "Infinity") if t in body], (path, body)
    finally:
        pg.close()
