"""Fleet mode: the local journal stays the first and durable home of every hit; a drainer in
the daemon's event loop copies what it commits to the PostgreSQL fleet store, and catches up
after an outage.

How nothing is lost or duplicated: TEMP triggers (daemon/store/schema.py) add an outbox row in
the same SQLite transaction as each write, so a committed hit is always either in the outbox or
already copied. The drainer copies one run per PostgreSQL transaction (an import arrives all or
nothing), and deletes the outbox rows only after PostgreSQL acknowledged the commit; a crash in
between copies them again, which the store's idempotent writes turn into a no-op. While the
server is unreachable the outbox grows (the run goes on) and the drainer retries with backoff;
its state (``status()``) says how far behind the fleet store is.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import Iterable
from typing import Any

import psycopg

from daemon.store import map_results, pg_maps, pg_temperatures
from daemon.store.journal import Store, StoreError
from daemon.store.pg import (
    CENTRE_COLS,
    HIT_COLS,
    MACHINE_COLS,
    RUN_COLS,
    PgStore,
    RunBatch,
    RunIdCollision,
)
from daemon.store.schema import CAPTURE_TRIGGERS, QUEUE_TEMPERATURES
from daemon.store.url import redact

log = logging.getLogger("rumba.drain")

BATCH_ROWS = 5000  # outbox rows looked at per pass (a run's rows are always taken whole)
WRITE_TIMEOUT_S = 60.0  # one run's transaction; beyond it the connection is presumed dead
BACKOFF_S = (0.2, 0.5, 1.0, 2.0, 5.0, 10.0)


class Drainer:
    """Copies the local journal's new rows to the fleet store, forever, in the event loop."""

    def __init__(self, store: Store, dsn: str, *, app: str = "rumba") -> None:
        self.store, self.dsn, self.app = store, dsn, app
        self.pg: PgStore | None = None
        self.wake = asyncio.Event()
        self._draining = asyncio.Lock()  # drain() never overlaps itself (one connection)
        self.copied_hits = 0
        self.last_error = ""
        self.last_copy_at: float | None = None
        self.commit_s: list[float] = []  # per-transaction PostgreSQL commit time (benchmarks)
        self.quarantined: set[str] = set()  # run ids refused by the store (never merged)
        self._task: asyncio.Task | None = None
        self._stopping = False
        self._loop = asyncio.get_running_loop()
        store.db.create_function("rumba_outbox_wake", 0, self._wake_soon, deterministic=False)
        for stmt in CAPTURE_TRIGGERS:
            store.db.execute(stmt)
        store.db.execute(QUEUE_TEMPERATURES)

    def _wake_soon(self) -> None:
        # Called by SQLite inside the writing statement (any thread): set the event later, in
        # the loop, once the write's transaction has committed and the writer has yielded.
        # Never raises: an exception here would fail the hit's INSERT (a closed loop at exit).
        with contextlib.suppress(RuntimeError):
            self._loop.call_soon_threadsafe(self.wake.set)

    # ----------------------------------------------------------------------------- control
    def start(self) -> None:
        self.wake.set()  # copy what a previous life left in the outbox
        self._task = self._loop.create_task(self._forever(), name="fleet-drain")

    async def stop(self, flush_timeout_s: float = 3.0) -> None:
        """Last copy attempt (bounded), then close; what is left stays in the outbox."""
        if self._task is not None:
            # The flag as well as the cancel: Python 3.11's wait_for loses a cancellation that
            # arrives as the awaited event is set (gh-86296), and the loop would run on.
            self._stopping = True
            self._task.cancel()
            self.wake.set()
            with contextlib.suppress(BaseException):
                await self._task
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.drain(), flush_timeout_s)
        await self._disconnect()

    def backlog(self) -> int:
        return int(self.store.db.execute("SELECT COUNT(*) FROM outbox").fetchone()[0])

    def status(self) -> dict[str, Any]:
        return {"connected": self.pg is not None, "backlog_rows": self.backlog(),
                "copied_hits": self.copied_hits, "last_error": self.last_error,
                "last_copy_at": self.last_copy_at, "store": redact(self.dsn),
                "quarantined_runs": sorted(self.quarantined)}

    def declare_machines(self, rows: Iterable[tuple]) -> None:
        """(name, site, dialect, transport, limits JSON) of each configured machine: written
        locally (the trigger queues them) so the fleet page knows machines before their first
        run, with their limits."""
        with self.store.transaction():
            for row in rows:
                self.store.db.execute(
                    f"INSERT INTO machines ({', '.join(MACHINE_COLS)}) VALUES (?,?,?,?,?,?)"
                    " ON CONFLICT(name) DO UPDATE SET site=excluded.site,"
                    " dialect=excluded.dialect, transport=excluded.transport,"
                    " limits=excluded.limits, updated_at=excluded.updated_at",
                    (*row, time.time()))

    # -------------------------------------------------------------------------------- loop
    async def _forever(self) -> None:
        failures = 0
        while not self._stopping:
            with contextlib.suppress(TimeoutError):
                # the wake-up normally comes from the trigger; the timeout is a safety net
                await asyncio.wait_for(self.wake.wait(), 5.0)
            self.wake.clear()
            try:
                await self.drain()
                failures = 0
            except (psycopg.Error, OSError, TimeoutError, StoreError) as e:
                msg = " ".join(str(e).split()) or type(e).__name__
                if msg != self.last_error:
                    log.warning("fleet store %s unreachable, journaling locally (%d rows to "
                                "copy): %s", redact(self.dsn), self.backlog(), msg)
                self.last_error = msg
                await self._disconnect()
                await asyncio.sleep(BACKOFF_S[min(failures, len(BACKOFF_S) - 1)])
                failures += 1
                self.wake.set()

    async def _disconnect(self) -> None:
        if self.pg is not None:
            pg, self.pg = self.pg, None
            with contextlib.suppress(Exception):
                await asyncio.wait_for(pg.close(), 2.0)

    async def drain(self) -> int:
        """Copy everything in the outbox now; returns the number of outbox rows copied. One
        drain at a time: the background loop and a caller (shutdown, a test) share one
        PostgreSQL connection, and two transactions interleaved on it end in psycopg's
        OutOfOrderTransactionNesting (seen under load)."""
        async with self._draining:
            total = 0
            while True:
                n = await self._pass()
                if n == 0:
                    return total
                total += n

    async def _pass(self) -> int:
        db = self.store.db
        skip = sorted(self.quarantined)
        rows = db.execute("SELECT DISTINCT kind = 'machines', key FROM (SELECT kind, key FROM"
                          f" outbox WHERE key NOT IN ({','.join('?' * len(skip))})"
                          " ORDER BY seq LIMIT ?)", (*skip, BATCH_ROWS)).fetchall()
        maps = map_results.pending(self.store)  # flagged, not queued: see map_results.pending
        if not rows and not maps:
            return 0
        if self.pg is None:
            self.pg = await PgStore.connect(self.dsn, app=self.app)
            if self.last_error:
                log.info("fleet store %s reachable again; copying %d rows", redact(self.dsn),
                         self.backlog())
            self.last_error = ""
        copied = await self._copy_maps(maps)
        for is_machine, key in rows:
            top = db.execute("SELECT MAX(seq), COUNT(*) FROM outbox WHERE key=? AND"
                             f" kind {'=' if is_machine else '!='} 'machines'",
                             (key,)).fetchone()
            if top[0] is None:
                continue
            t0 = time.perf_counter()
            try:
                if is_machine:
                    await asyncio.wait_for(self._copy_machine(key), WRITE_TIMEOUT_S)
                else:
                    await asyncio.wait_for(self._copy_run(key, top[0]), WRITE_TIMEOUT_S)
            except RunIdCollision as e:
                log.error("%s; its rows stay in the local journal", e)
                self.quarantined.add(key)
                continue
            self.commit_s.append(time.perf_counter() - t0)
            db.execute(f"DELETE FROM outbox WHERE key=? AND seq<=? AND kind "
                       f"{'=' if is_machine else '!='} 'machines'", (key, top[0]))
            copied += top[1]
            self.last_copy_at = time.time()
        return copied

    async def _copy_maps(self, rows: list[tuple]) -> int:
        """Each map result in its own statement (autocommit), then flagged copied (or refused:
        its id is another machine's, logged once, kept locally)."""
        for row in rows:
            assert self.pg is not None
            ok = await asyncio.wait_for(pg_maps.write(self.pg.conn, row), WRITE_TIMEOUT_S)
            if not ok:
                log.error("map result %s already in the fleet store for another machine than "
                          "%s: not copied; it stays in the local journal", row[0], row[1])
            map_results.mark_copied(self.store, row[0], row[3], refused=not ok)
        return len(rows)

    async def _copy_machine(self, name: str) -> None:
        row = self.store.db.execute(f"SELECT {', '.join(MACHINE_COLS)} FROM machines WHERE"
                                    " name=?", (name,)).fetchone()
        if row is not None and self.pg is not None:
            await self.pg.write_machine(tuple(row))

    async def _copy_run(self, run_id: str, upto: int) -> None:
        db = self.store.db
        kinds = dict(db.execute(
            "SELECT kind, json_group_array(hit_seq) FROM outbox WHERE key=? AND seq<=?"
            " GROUP BY kind", (run_id, upto)).fetchall())
        run = db.execute(f"SELECT {', '.join(RUN_COLS)} FROM runs WHERE id=?",
                         (run_id,)).fetchone()
        if run is None:  # rolled back after queuing cannot happen (same transaction); be safe
            return
        b = RunBatch(run=tuple(run))
        if "hits" in kinds:
            seqs = [s for s in json.loads(kinds["hits"]) if s is not None]
            b.hits = db.execute(f"SELECT {', '.join(HIT_COLS)} FROM hits WHERE run_id=? AND"
                                " seq BETWEEN ? AND ?", (run_id, min(seqs), max(seqs))).fetchall()
        if "temperatures" in kinds:  # the raw readings, journaled like hits
            seqs = [s for s in json.loads(kinds["temperatures"]) if s is not None]
            b.temperatures = db.execute(
                f"SELECT {', '.join(pg_temperatures.TEMP_COLS)} FROM temperatures WHERE"
                " run_id=? AND seq BETWEEN ? AND ?", (run_id, min(seqs), max(seqs))).fetchall()
        if "centres" in kinds:
            b.centres = db.execute(f"SELECT {', '.join(CENTRE_COLS)} FROM centres WHERE"
                                   " run_id=?", (run_id,)).fetchall()
        if "estimates" in kinds:
            r = db.execute("SELECT analysis FROM estimates WHERE run_id=?", (run_id,)).fetchone()
            b.analysis = r[0] if r else None
        if "estimates" in kinds or "link_estimates" in kinds:
            # the link estimate goes with its analysis: written by the run's worker thread on
            # a connection of its own (no capture trigger there), just before the analysis
            b.link_estimate = db.execute("SELECT model_key, estimate, plan, created_at FROM"
                                         " link_estimates WHERE run_id=?",
                                         (run_id,)).fetchone()
        if "verdicts" in kinds:
            b.verdict = db.execute("SELECT status, reasons, checks, written_back FROM verdicts"
                                   " WHERE run_id=?", (run_id,)).fetchone()
        if "reports" in kinds:
            b.report = db.execute("SELECT html_path, json_path FROM reports WHERE run_id=?",
                                  (run_id,)).fetchone()
        if "report_jobs" in kinds:  # the report's own end (migration 10), apart from the run
            b.report_job = db.execute("SELECT state, reason, started_at, ended_at FROM"
                                      " report_jobs WHERE run_id=?", (run_id,)).fetchone()
        if "baselines" in kinds:  # who proposed / confirmed this run as a baseline
            b.baselines = db.execute("SELECT machine, run_id, state, by_person, at, note FROM"
                                     " baselines WHERE run_id=? ORDER BY id",
                                     (run_id,)).fetchall()
        assert self.pg is not None
        await self.pg.write_run(b)
        self.copied_hits += len(b.hits)
