"""The fleet page over a real PostgreSQL shows each run's temperature channels: the
summary the daemon drained with the run's analysis; garbage costs the cell, never the page."""

from __future__ import annotations

import json
import time

import aiohttp
import pytest

from daemon.fleet import view
from daemon.store.pg import RUN_COLS, PgStore, RunBatch
from tests.fleet_helpers import fresh_db, start_postgres
from tests.test_fleet_page import TOKEN, serving

pytestmark = [pytest.mark.peer]


def row(run_id: str, started: float) -> tuple:
    values = {"id": run_id, "machine": "mill-t", "trigger": "cnc", "state": "DONE",
              "reason": "", "plan": "p", "artefact": "a", "dialect": "fanuc",
              "touch_total": 140, "started_at": started, "ended_at": started + 200,
              "verdict": "WARN", "summary": "", "imported": 0, "started_by": ""}
    return tuple(values[c] for c in RUN_COLS)


async def test_run_temperatures_on_the_machine_page(tmp_path):
    pg = start_postgres()
    try:
        dsn = fresh_db(pg)
        store = await PgStore.connect(dsn)
        now = time.time()
        temps = {"spindle": {"source": "spindle: opcua /T", "start_c": 20.54, "end_c": 24.06,
                             "change_c": 3.52},
                 "column": {"source": "column: modbus-tcp", "start_c": None, "end_c": None}}
        await store.write_run(RunBatch(run=row("T-1", now - 3600), analysis=json.dumps(
            {"machine": "m", "links": {}, "temperatures": temps})))
        await store.write_run(RunBatch(run=row("T-2", now - 1800), analysis=json.dumps(
            {"machine": "m", "links": {}, "temperatures": {"x": "junk", "y": {"start_c": "a"}}})))
        runs = await store.runs("mill-t", 10)
        await store.close()
        assert runs[1]["temperatures"] == temps  # as stored
        async with serving(dsn, tmp_path) as url, aiohttp.ClientSession(
                headers={"Authorization": f"Bearer {TOKEN}"}) as http, \
                http.get(f"{url}/machines/mill-t") as r:
            page = await r.text()
            assert r.status == 200, page
        assert "<th>Temperatures</th>" in page
        # the channels in the analysis' order (as the report prints them)
        assert "spindle 20.5 → 24.1 °C (+3.5 °C); column not read" in page
        assert "x not read; y not read" in page
    finally:
        pg.close()


def test_temperature_cell_of_garbage():
    assert view.temperatures_text(None) == "" and view.temperatures_text([1, 2]) == ""
    assert view.temperatures_text({"s": {"start_c": float("nan"), "end_c": 1.0}}) == \
        "s not read"
