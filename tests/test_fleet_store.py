"""Fleet store on a real PostgreSQL: same schema as the journal, many daemons at once, nothing
lost or duplicated, an outage mid-run drained afterwards, imports all or nothing, run-id
collisions refused, INTERRUPTED runs reach the fleet."""

from __future__ import annotations

import asyncio
import sqlite3

import psycopg
import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
from contracts.messages import ProbeHit
from contracts.yaml_files import ConfigError
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.run.session import Session, State
from daemon.store.drain import Drainer
from daemon.store.journal import Store, StoreError
from daemon.store.pg import PgStore
from daemon.store.schema import SCHEMA_VERSION
from daemon.store.url import parse_store_url, redact
from tests.fleet_helpers import fresh_db, start_postgres, until

peer = pytest.mark.peer


@pytest.fixture(scope="module")
def pg():
    server = start_postgres()
    yield server
    server.close()


def hit(seq: int) -> ProbeHit:
    return ProbeHit(seq=seq, pose=seq // 20, ball="B1", touch=1 + seq % 5,
                    axes={"X": 1.5 * seq, "Y": -2.0, "Z": 3.25, "B": 30.0, "C": 60.0},
                    triggered=True, t_s=0.1 * seq, raw=f"#{seq}", direction=(1.0, 0, 0),
                    feed_mm_min=300.0, extra={"q": 1.0})


def pg_rows(dsn: str, q: str, args: tuple = ()) -> list[tuple]:
    with psycopg.connect(dsn) as c:
        return c.execute(q, args).fetchall()  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ no server
def test_store_urls_are_checked():
    assert parse_store_url("sqlite:///var/j.sqlite", "k").path.as_posix() == "var/j.sqlite"
    assert parse_store_url("postgresql://rumba@db:5432/fleet?sslmode=verify-full", "k").kind \
        == "postgresql"
    for bad, why in (("mysql://x/y", "unsupported store URL"), ("sqlite:///", "without a path"),
                     ("postgresql://u:hunter2@db/x", "carries a password"),
                     ("postgresql://db/x?bogus=1", "invalid PostgreSQL URL")):
        with pytest.raises(ConfigError, match=why) as e:
            parse_store_url(bad, "daemon.yaml: store.url")
        assert "hunter2" not in str(e.value) and str(e.value).startswith("daemon.yaml: store.url")
    assert redact("postgresql://u:pw@h/d") == "postgresql://u:***@h/d"


# --------------------------------------------------------------------------------- server
@peer
async def test_postgres_gets_the_journals_schema_and_migrates_once(pg, tmp_path):
    dsn = fresh_db(pg)
    first, second = await asyncio.gather(PgStore.connect(dsn), PgStore.connect(dsn))
    assert await first.schema_version() == SCHEMA_VERSION
    await first.close()
    await second.close()
    lite = Store(tmp_path / "j.sqlite")
    tables = [r[0] for r in lite.db.execute("SELECT name FROM sqlite_master WHERE type='table'"
                                            " AND name NOT LIKE 'sqlite_%'")]
    for t in tables:
        local = [r[1] for r in lite.db.execute(f"PRAGMA table_info({t})")]
        remote = [r[0] for r in pg_rows(dsn, "SELECT column_name FROM information_schema.columns"
                                        " WHERE table_name=%s ORDER BY ordinal_position", (t,))]
        assert local == remote, t
    assert pg_rows(dsn, "SELECT COUNT(*) FROM schema_version")[0][0] == SCHEMA_VERSION
    lite.close()


@peer
async def test_many_daemons_at_once_lose_and_duplicate_nothing(pg, tmp_path):
    dsn = fresh_db(pg)
    daemons = []
    for k in range(4):
        s = Store(tmp_path / f"d{k}.sqlite")
        d = Drainer(s, dsn, app=f"d{k}")
        d.start()
        daemons.append((s, d))

    async def machine(k: int, s: Store) -> None:
        for r in range(2):
            rid = f"R{k}-{r}"
            s.new_run(rid, f"mill{k}", "cnc", touch_total=150)
            for seq in range(1, 151):
                s.journal_hit(rid, hit(seq))
                await asyncio.sleep(0)  # interleave the daemons' writes and their copies
            s.set_state(rid, "DONE")

    await asyncio.gather(*(machine(k, s) for k, (s, _) in enumerate(daemons)))
    for _s, d in daemons:
        await until(lambda d=d: d.backlog() == 0, what="outbox empty")
    counts = pg_rows(dsn, "SELECT run_id, COUNT(*), COUNT(DISTINCT seq), MIN(seq), MAX(seq)"
                     " FROM hits GROUP BY run_id ORDER BY run_id")
    assert counts == [(f"R{k}-{r}", 150, 150, 1, 150) for k in range(4) for r in range(2)]
    assert {r[0] for r in pg_rows(dsn, "SELECT state FROM runs")} == {"DONE"}
    # a lost acknowledgement: the same rows queued and copied again change nothing
    s, d = daemons[0]
    s.db.execute("INSERT INTO outbox(kind, key, hit_seq) SELECT 'hits', run_id, seq FROM hits")
    await d.drain()
    assert pg_rows(dsn, "SELECT COUNT(*) FROM hits")[0][0] == 4 * 2 * 150
    for s, d in daemons:
        await d.stop()
        s.close()


@peer
async def test_server_stopped_mid_run_hits_are_journaled_locally_then_drained(pg, tmp_path):
    """The run goes on while PostgreSQL is down (pg_ctl stop -m fast at touch 30), ends with
    its verdict, and every hit reaches the fleet store once after the restart."""
    dsn = fresh_db(pg)
    setup = thesis_setup()
    rows = thesis_rows(setup)
    store = Store(tmp_path / "j.sqlite")
    drainer = Drainer(store, dsn)
    drainer.start()
    session = Session(setup, ReplayLink(rows, setup.machine), store, tmp_path / "reports",
                      prepare=prepare_from_rows(rows))
    stopped: list[int] = []

    def on_status(st: dict) -> None:
        if st["done"] == 30 and not stopped:
            pg.stop("fast")  # the server goes away mid-capture
            stopped.append(drainer.backlog())

    session.listeners.append(on_status)
    try:
        run_id = session.start("cli")
        final = await session.wait()
        assert stopped and final["state"] == State.IDLE and final["verdict"]["status"]
        assert store.hit_count(run_id) == len(rows)  # the journal never missed a hit
        await until(lambda: drainer.last_error != "", what="the drainer to notice the outage")
        assert drainer.backlog() > len(rows) - 30 and not drainer.status()["connected"]
    finally:
        pg.start()
    await until(lambda: drainer.backlog() == 0, what="the backlog to drain")
    got = pg_rows(dsn, "SELECT COUNT(*), COUNT(DISTINCT seq) FROM hits WHERE run_id=%s",
                  (run_id,))[0]
    assert got == (len(rows), len(rows))
    assert pg_rows(dsn, "SELECT r.state, r.verdict, v.written_back FROM runs r JOIN verdicts v"
                   " ON v.run_id = r.id WHERE r.id=%s", (run_id,)) == \
        [("DONE", final["verdict"]["status"], 1)]
    local = [tuple(h) for h in store.db.execute("SELECT seq, raw, axes FROM hits WHERE run_id=?"
                                                " ORDER BY seq", (run_id,))]
    assert pg_rows(dsn, "SELECT seq, raw, axes FROM hits WHERE run_id=%s ORDER BY seq",
                   (run_id,)) == local
    await drainer.stop()
    store.close()


@peer
async def test_import_is_all_or_nothing_and_interrupted_runs_reach_the_fleet(pg, tmp_path):
    dsn = fresh_db(pg)
    store = Store(tmp_path / "j.sqlite")
    drainer = Drainer(store, dsn)
    with pytest.raises(sqlite3.IntegrityError), store.transaction():
        store.new_run("IMP1", "mill1", "import", state="IMPORTED", imported=True)
        store.journal_hits("IMP1", [hit(1), hit(2), hit(2)])  # a duplicated seq: refused
    assert drainer.backlog() == 0  # the rolled-back import queued nothing
    with store.transaction():
        store.new_run("IMP2", "mill1", "import", state="IMPORTED", imported=True)
        store.journal_hits("IMP2", [hit(k) for k in range(1, 7001)])  # > one outbox pass
    store.new_run("CUT", "mill1", "cnc")
    store.set_state("CUT", "CAPTURE")
    store.journal_hit("CUT", hit(1))
    await drainer.drain()
    assert pg_rows(dsn, "SELECT id, state FROM runs ORDER BY id") == [("CUT", "CAPTURE"),
                                                                      ("IMP2", "IMPORTED")]
    assert pg_rows(dsn, "SELECT COUNT(*) FROM hits WHERE run_id='IMP2'")[0][0] == 7000
    assert store.mark_interrupted() == ["CUT"]  # what the next daemon start does
    await drainer.drain()
    assert pg_rows(dsn, "SELECT state FROM runs WHERE id='CUT'") == [("INTERRUPTED",)]
    await drainer.stop()
    store.close()


@peer
async def test_a_runs_link_estimate_reaches_the_fleet_with_its_analysis(pg, tmp_path):
    """Migration 6: the run's estimate for its compensation view is written by the
    run's worker thread on a connection of its own (no capture trigger there), just before
    the analysis; it is copied with the analysis, and when written on the daemon's own
    connection later (a run journaled before the migration), by its own trigger."""
    dsn = fresh_db(pg)
    store = Store(tmp_path / "j.sqlite")
    drainer = Drainer(store, dsn)
    worker = Store(tmp_path / "j.sqlite")
    for rid in ("R1", "R2"):
        store.new_run(rid, "mill1", "cnc")
    worker.db.execute("INSERT INTO link_estimates VALUES ('R1', 'k1', '{\"p\": 1}', '{}', 1.5)")
    store.db.execute("INSERT INTO estimates VALUES ('R1', '{\"links\": {}}')")
    await drainer.drain()
    assert pg_rows(dsn, "SELECT run_id, model_key, estimate, plan, created_at FROM"
                   " link_estimates") == [("R1", "k1", '{"p": 1}', "{}", 1.5)]
    store.db.execute("INSERT INTO link_estimates VALUES ('R2', 'k2', '{\"p\": 2}', '{}', 2.5)")
    store.db.execute("UPDATE link_estimates SET model_key='k1b' WHERE run_id='R1'")
    await drainer.drain()
    assert pg_rows(dsn, "SELECT run_id, model_key FROM link_estimates ORDER BY run_id") == [
        ("R1", "k1b"), ("R2", "k2")]
    # the other one-row-per-run tables go the same way (one upsert for all four)
    store.save_verdict("R1", "PASS", ["ok"], [{"name": "EX0C"}], "all within")
    store.save_report("R1", tmp_path / "R1.html", tmp_path / "R1.json")
    store.save_verdict("R1", "WARN", ["drift"], [], "again")
    await drainer.drain()
    assert pg_rows(dsn, "SELECT run_id, status, reasons, checks, written_back FROM verdicts") \
        == [("R1", "WARN", '["drift"]', "[]", 0)]
    assert pg_rows(dsn, "SELECT run_id, html_path, json_path FROM reports") == [
        ("R1", str(tmp_path / "R1.html"), str(tmp_path / "R1.json"))]
    assert pg_rows(dsn, "SELECT analysis FROM estimates") == [('{"links": {}}',)]
    # the baseline decisions reach the fleet store, each once (the fleet numbers
    # them: several daemons' local ids would collide)
    for state, by, at in (("proposed", "rumba", 10.5), ("confirmed", "Anna Berg", 11.5)):
        store.db.execute("INSERT INTO baselines (machine, run_id, state, by_person, at, note)"
                         " VALUES ('mill1', 'R1', ?, ?, ?, 'after the service')", (state, by, at))
        await drainer.drain()
    store.save_verdict("R1", "PASS", [], [], "again")  # the run copied again: no duplicate
    await drainer.drain()
    assert pg_rows(dsn, "SELECT machine, run_id, state, by_person, at, note FROM baselines"
                   " ORDER BY at") == [
        ("mill1", "R1", "proposed", "rumba", 10.5, "after the service"),
        ("mill1", "R1", "confirmed", "Anna Berg", 11.5, "after the service")]
    await drainer.stop()
    worker.close()
    store.close()


@peer
async def test_a_run_id_taken_by_another_machine_is_refused_not_merged(pg, tmp_path):
    dsn = fresh_db(pg)
    a, b = Store(tmp_path / "a.sqlite"), Store(tmp_path / "b.sqlite")
    da, db_ = Drainer(a, dsn), Drainer(b, dsn)
    a.new_run("SAME", "mill1", "cnc")
    a.journal_hit("SAME", hit(1))
    b.new_run("SAME", "mill2", "cnc")
    b.journal_hit("SAME", hit(1))
    b.journal_hit("SAME", hit(2))
    b.new_run("OTHER", "mill2", "cnc")
    await da.drain()
    await db_.drain()
    assert pg_rows(dsn, "SELECT id, machine FROM runs ORDER BY id") == [("OTHER", "mill2"),
                                                                        ("SAME", "mill1")]
    assert pg_rows(dsn, "SELECT COUNT(*) FROM hits")[0][0] == 1
    assert db_.status()["quarantined_runs"] == ["SAME"] and db_.backlog() == 3  # kept locally
    for d, s in ((da, a), (db_, b)):
        await d.stop()
        s.close()


@peer
async def test_unreachable_store_at_start_is_an_error_the_drainer_retries(pg, tmp_path):
    store = Store(tmp_path / "j.sqlite")
    dead = f"postgresql://rumba@127.0.0.1:{pg.port}/no_such_db"
    with pytest.raises(StoreError, match="no_such_db"):
        await PgStore.connect(dead)
    drainer = Drainer(store, dead)
    drainer.start()
    store.new_run("R1", "mill1", "cnc")
    store.journal_hit("R1", hit(1))  # journaling never waits for the fleet store
    await until(lambda: "no_such_db" in drainer.last_error, what="the error")
    assert drainer.backlog() == 2
    await drainer.stop(flush_timeout_s=0.5)
    store.close()


@peer
async def test_a_map_job_done_without_a_verdict_is_not_the_machines_last_verdict(pg, tmp_path):
    """A map job ends DONE without a verdict (it maps the axes, it judges nothing): the fleet's
    last verdict stays the last check's, and the machine page shows no ERROR for it; a run
    that failed still is one."""
    from daemon.fleet.view import machine_page

    dsn = fresh_db(pg)
    store = Store(tmp_path / "j.sqlite")
    drainer = Drainer(store, dsn)
    try:
        store.new_run("CHECK", "mill1", "cnc")
        store.save_verdict("CHECK", "PASS", [], [], "all within")
        store.set_state("CHECK", "DONE")
        store.new_run("MAP", "mill1", "hmi")
        store.set_state("MAP", "DONE", "map of the linear axes")
        await drainer.drain()
        pgs = await PgStore.connect(dsn, migrate=False)
        try:
            (row,) = await pgs.fleet()
            assert (row["run_id"], row["verdict"], row["current_run"]) == ("CHECK", "PASS", "MAP")
            runs = await pgs.runs("mill1", 10)
            page = machine_page("mill1", await pgs.machine("mill1"), runs, [], 30)
            assert page.count('class="badge ERROR"') == 0 and 'class="badge PASS"' in page
            store.new_run("BROKEN", "mill1", "cnc")
            store.set_state("BROKEN", "FAILED", "link lost")
            await drainer.drain()
            (row,) = await pgs.fleet()
            assert (row["run_id"], row["verdict"]) == ("BROKEN", "ERROR")
            page = machine_page("mill1", await pgs.machine("mill1"), await pgs.runs("mill1", 10),
                                [], 30)
            assert page.count('class="badge ERROR"') == 1
        finally:
            await pgs.close()
    finally:
        await drainer.stop()
        store.close()
