"""Map results in the fleet store (real PostgreSQL on loopback): a map journaled by
``rumba map --store`` (another connection, no capture trigger) is copied by the daemon's
drainer once, with its figures; a map id of another machine is refused, never merged; the fleet
page shows a machine's maps and answers them as JSON."""

from __future__ import annotations

import json

import aiohttp
import psycopg
import pytest

from daemon.store import map_results, pg_maps
from daemon.store.drain import Drainer
from daemon.store.journal import Store
from daemon.store.pg import PgStore
from tests.fleet_helpers import fresh_db, pg  # noqa: F401 (pg: the module's server)
from tests.map_result_helpers import journaled_map
from tests.test_fleet_page import TOKEN, serving
from tests.test_map_cli import files  # noqa: F401 (files: the fixture)

pytestmark = [pytest.mark.peer]


@pytest.fixture
def journaled(files, tmp_path_factory):  # noqa: F811
    # one journal per test: the tests mark its maps copied and add maps (in a shuffled order
    # a shared one reached the drainer test already drained)
    tmp = tmp_path_factory.mktemp("mapfleet")
    _, mjson, rep, _ = journaled_map(tmp, files[1])
    return tmp, mjson, rep


def pg_rows(dsn: str, q: str) -> list[tuple]:
    with psycopg.connect(dsn) as c:
        return c.execute(q).fetchall()  # type: ignore[arg-type]


async def test_the_drainer_copies_a_map_once_with_its_figures(pg, journaled):  # noqa: F811
    tmp, mjson, rep = journaled
    dsn = fresh_db(pg)
    store = Store(tmp / "journal.sqlite")
    drainer = Drainer(store, dsn)
    try:
        (local,) = map_results.listed(store)
        assert map_results.pending(store)  # written by the CLI: waiting for the drainer
        await drainer.drain()
        assert map_results.pending(store) == []
        got = pg_rows(dsn, "SELECT id, machine, verdict, volumetric_max_um, volumetric_rms_um,"
                           " json_sha256, figures FROM map_results")
        assert len(got) == 1
        mid, machine, verdict, vmax, vrms, sha, figs = got[0]
        assert (mid, machine, verdict, sha) == (local.id, "mill1", "WARN", local.json_sha256)
        assert vmax == pytest.approx(local.volumetric_max_um, rel=1e-12)
        assert vrms == pytest.approx(local.volumetric_rms_um, rel=1e-12)
        assert json.loads(figs) == local.figures
        # a second map (a later `rumba map --store`, its own connection) and a drain again:
        # the new one copied, the first not twice
        other = Store(tmp / "journal.sqlite")
        second = map_results.record_map_result(other, None, mjson, rep, machine="mill1")
        other.close()
        await drainer.drain()
        assert sorted(r[0] for r in pg_rows(dsn, "SELECT id FROM map_results")) == sorted(
            [local.id, second.id])
        conn = await PgStore.connect(dsn, migrate=False)
        try:
            assert (await pg_maps.last(conn.conn, "mill1")).id == second.id
            latest = await pg_maps.latest_per_machine(conn.conn)
            assert latest["mill1"]["volumetric_max_um"] == pytest.approx(
                second.volumetric_max_um)
        finally:
            await conn.close()
    finally:
        await drainer.stop()
        store.close()


async def test_a_map_id_of_another_machine_is_refused_not_merged(pg, journaled,  # noqa: F811
                                                                 tmp_path):
    _, mjson, rep = journaled
    dsn = fresh_db(pg)
    a, b = Store(tmp_path / "a.sqlite"), Store(tmp_path / "b.sqlite")
    for s, machine in ((a, "mill1"), (b, "mill2")):
        s.new_run("MAPJOB-1", machine, "hmi", state="DONE")
        map_results.record_map_result(s, "MAPJOB-1", mjson, rep)
    da, db_ = Drainer(a, dsn), Drainer(b, dsn)
    try:
        await da.drain()
        await db_.drain()
        assert pg_rows(dsn, "SELECT id, machine FROM map_results") == [("MAPJOB-1", "mill1")]
        flags = b.db.execute("SELECT fleet_copied FROM map_results").fetchall()
        assert flags == [(map_results.REFUSED,)]  # kept locally, not retried forever
        assert map_results.pending(b) == []
    finally:
        for d, s in ((da, a), (db_, b)):
            await d.stop()
            s.close()


async def test_the_fleet_page_shows_a_machines_maps(pg, journaled, tmp_path):  # noqa: F811
    tmp, _, _ = journaled
    dsn = fresh_db(pg)
    store = Store(tmp / "journal.sqlite")
    store.db.execute("UPDATE map_results SET fleet_copied=0")  # copy again to this database
    drainer = Drainer(store, dsn)
    try:
        await drainer.drain()
        maps = map_results.listed(store, "mill1")
    finally:
        await drainer.stop()
        store.close()
    async with serving(dsn, tmp_path) as url, aiohttp.ClientSession(
            headers={"Authorization": f"Bearer {TOKEN}"}) as http:
        async with http.get(f"{url}/api/machines/mill1/maps") as r:
            assert r.status == 200
            d = await r.json()
        assert [m["id"] for m in d["maps"]] == [m.id for m in maps]
        first = d["maps"][0]
        assert first["kind"] == "map" and first["verdict"] == "WARN"
        assert first["volumetric_max_um"] == pytest.approx(maps[0].volumetric_max_um)
        assert "json_path" not in first  # the daemon's paths stay the daemon's
        async with http.get(f"{url}/machines/mill1") as r:
            assert r.status == 200
            html = await r.text()
        assert "Maps of the linear axes" in html and maps[0].id in html
        assert f"{maps[0].volumetric_max_um:.1f} ± {maps[0].volumetric_max_u_um:.1f}" in html
        async with http.get(f"{url}/api/machines/no..such/maps") as r:
            assert r.status == 200 and (await r.json())["maps"] == []
        async with http.get(f"{url}/api/machines/mill1/maps?limit=0") as r:
            assert r.status == 400
