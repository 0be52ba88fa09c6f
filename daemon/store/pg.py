"""The fleet store: the journal's tables in one PostgreSQL shared by many daemons (psycopg 3,
async), written by each daemon's drainer and read by the fleet page.

Same migrations as the SQLite journal (daemon/store/schema.py). Daemons starting together
serialise their migrations on an advisory lock. Writes are idempotent (hits ``ON CONFLICT DO
NOTHING``, the other rows upserted to the daemon's current copy), so a batch copied twice after
a lost acknowledgement leaves one row; a run id already owned by another machine is refused,
never merged.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import Any

import psycopg
from psycopg import conninfo

from daemon.store import pg_temperatures
from daemon.store.journal import StoreError
from daemon.store.schema import MIGRATIONS, SCHEMA_VERSION, for_postgres
from daemon.store.stored_json import analysis_part
from daemon.store.url import redact

_MIGRATION_LOCK = 0x72756D6261  # "rumba": pg_advisory_xact_lock key for migrations

RUN_COLS = ("id", "machine", "trigger", "state", "reason", "plan", "artefact", "dialect",
            "touch_total", "started_at", "ended_at", "verdict", "summary", "imported", "started_by")
HIT_COLS = ("run_id", "seq", "t_s", "repeat", "pose", "b_cmd_deg", "c_cmd_deg", "ball", "touch",
            "dir_x", "dir_y", "dir_z", "axes", "triggered", "feed_mm_min", "raw", "extra",
            "received_at")
CENTRE_COLS = ("run_id", "pose", "ball", "b_deg", "c_deg", "x_mm", "y_mm", "z_mm",
               "radius_dev_um", "form_um")
MACHINE_COLS = ("name", "site", "dialect", "transport", "limits", "updated_at")


class RunIdCollision(StoreError):
    """A run id in the fleet store belongs to another machine or start (never merged)."""


# the tables with one row per run (after run_id, in their column order)
_RUN_ROW_COLS = {"estimates": ("analysis",),
                 "link_estimates": ("model_key", "estimate", "plan", "created_at"),
                 "verdicts": ("status", "reasons", "checks", "written_back"),
                 "reports": ("html_path", "json_path"),
                 "report_jobs": ("state", "reason", "started_at", "ended_at")}


@dataclass
class RunBatch:
    """One run's rows to copy in one PostgreSQL transaction (an import is all or nothing)."""

    run: tuple
    hits: list[tuple] = field(default_factory=list)
    centres: list[tuple] | None = None  # None: unchanged since the last copy
    analysis: str | None = None
    link_estimate: tuple | None = None  # (model_key, estimate, plan, created_at)
    verdict: tuple | None = None  # (status, reasons, checks, written_back)
    report: tuple | None = None  # (html_path, json_path)
    report_job: tuple | None = None  # (state, reason, started_at, ended_at)
    baselines: list[tuple] = field(default_factory=list)  # (machine, run_id, state, by, at, note)
    temperatures: list[tuple] = field(default_factory=list)  # pg_temperatures.TEMP_COLS


def _defaults(dsn: str, app: str, connect_timeout_s: float) -> str:
    """The URL plus what a daemon needs unless the URL says otherwise: a connect timeout and TCP
    keepalives (a cable pulled mid-run is noticed in ~10 s, not after the kernel's 2 hours)."""
    params = conninfo.conninfo_to_dict(dsn)
    for k, v in (("connect_timeout", str(max(1, round(connect_timeout_s)))),
                 ("application_name", app), ("keepalives", "1"), ("keepalives_idle", "5"),
                 ("keepalives_interval", "2"), ("keepalives_count", "3")):
        params.setdefault(k, v)
    return conninfo.make_conninfo(**params)


class PgStore:
    """One async connection to the fleet store (autocommit; explicit transactions)."""

    def __init__(self, conn: psycopg.AsyncConnection, dsn: str) -> None:
        self.conn = conn
        self.dsn = dsn

    @classmethod
    async def connect(cls, dsn: str, *, app: str = "rumba",
                      connect_timeout_s: float = 5.0, migrate: bool = True) -> PgStore:
        try:
            conn = await psycopg.AsyncConnection.connect(
                _defaults(dsn, app, connect_timeout_s), autocommit=True)
        except psycopg.Error as e:
            raise StoreError(f"fleet store {redact(dsn)}: {' '.join(str(e).split())}") from None
        store = cls(conn, dsn)
        if migrate:
            await store.migrate()
        return store

    async def close(self) -> None:
        await self.conn.close()

    # ------------------------------------------------------------------------------- schema
    async def migrate(self) -> None:
        async with self.conn.transaction():
            await self.conn.execute("SELECT pg_advisory_xact_lock(%s)", (_MIGRATION_LOCK,))
            await self.conn.execute("CREATE TABLE IF NOT EXISTS schema_version "
                                    "(version BIGINT PRIMARY KEY, applied_at DOUBLE PRECISION "
                                    "NOT NULL)")
            current = await self.schema_version()
            if current > SCHEMA_VERSION:
                raise StoreError(f"fleet store {redact(self.dsn)}: schema v{current} is newer "
                                 f"than this rumba (v{SCHEMA_VERSION}); upgrade rumba")
            for version in range(current + 1, SCHEMA_VERSION + 1):
                for stmt in MIGRATIONS[version - 1]:
                    await self.conn.execute(for_postgres(stmt))  # type: ignore[arg-type]
                await self.conn.execute("INSERT INTO schema_version VALUES (%s, %s)",
                                        (version, time.time()))

    async def schema_version(self) -> int:
        cur = await self.conn.execute("SELECT MAX(version) FROM schema_version")
        row = await cur.fetchone()
        return int(row[0] or 0) if row else 0

    # ------------------------------------------------------------------------------- writes
    async def write_run(self, b: RunBatch) -> None:
        """Copy one run's rows in one transaction; ``RunIdCollision`` if the id is taken."""
        cols = ", ".join(RUN_COLS)
        sets = ", ".join(f"{c}=EXCLUDED.{c}" for c in RUN_COLS[2:])
        async with self.conn.transaction(), self.conn.cursor() as cur:
            await cur.execute(
                f"INSERT INTO runs ({cols}) VALUES ({', '.join(['%s'] * len(RUN_COLS))})"
                f" ON CONFLICT (id) DO UPDATE SET {sets} WHERE runs.machine = EXCLUDED.machine"
                " AND runs.started_at = EXCLUDED.started_at RETURNING id", b.run)
            if await cur.fetchone() is None:
                raise RunIdCollision(f"run id {b.run[0]} already in the fleet store for another "
                                     f"machine or start than {b.run[1]}: not copied")
            if b.hits:
                await cur.executemany(
                    f"INSERT INTO hits ({', '.join(HIT_COLS)}) VALUES "
                    f"({', '.join(['%s'] * len(HIT_COLS))}) ON CONFLICT (run_id, seq) DO NOTHING",
                    b.hits)
            if b.centres is not None:
                await cur.execute("DELETE FROM centres WHERE run_id=%s", (b.run[0],))
                if b.centres:
                    await cur.executemany(
                        f"INSERT INTO centres ({', '.join(CENTRE_COLS)}) VALUES "
                        f"({', '.join(['%s'] * len(CENTRE_COLS))})", b.centres)
            await pg_temperatures.insert(cur, b.temperatures)  # raw readings
            # baseline decisions; the fleet store numbers them itself (several
            # daemons' local ids would collide), a row already copied is not copied again
            if b.baselines:
                await cur.executemany(
                    "INSERT INTO baselines (machine, run_id, state, by_person, at, note)"
                    " SELECT %s, %s, %s, %s, %s, %s WHERE NOT EXISTS (SELECT 1 FROM baselines"
                    " WHERE machine=%s AND run_id=%s AND state=%s AND at=%s)",
                    [(*r, r[0], r[1], r[2], r[4]) for r in b.baselines])
            for table, row in (("estimates", (b.analysis,) if b.analysis is not None else None),
                               ("link_estimates", b.link_estimate), ("verdicts", b.verdict),
                               ("reports", b.report), ("report_jobs", b.report_job)):
                if row is not None:  # one row per run, replaced by a newer copy
                    cols = _RUN_ROW_COLS[table]
                    await cur.execute(
                        f"INSERT INTO {table} VALUES ({', '.join(['%s'] * (len(cols) + 1))})"
                        f" ON CONFLICT (run_id) DO UPDATE SET "
                        f"{', '.join(f'{c}=EXCLUDED.{c}' for c in cols)}", (b.run[0], *row))

    async def write_machine(self, row: tuple) -> None:
        sets = ", ".join(f"{c}=EXCLUDED.{c}" for c in MACHINE_COLS[1:])
        await self.conn.execute(
            f"INSERT INTO machines ({', '.join(MACHINE_COLS)}) VALUES "
            f"({', '.join(['%s'] * len(MACHINE_COLS))}) ON CONFLICT (name) DO UPDATE SET {sets}",
            row)

    # -------------------------------------------------------------------------------- reads
    async def _all(self, q: str, args: tuple = ()) -> list[tuple]:
        cur = await self.conn.execute(q, args)  # type: ignore[arg-type]
        return await cur.fetchall()

    async def fleet(self) -> list[dict[str, Any]]:
        """Every known machine with its last run that reached a verdict or an error end, and
        its last run of any state (a run in progress), newest first per machine. A run done
        without a verdict (a map job: it maps, it does not judge the machine) is neither."""
        rows = await self._all(
            "WITH names AS (SELECT name FROM machines UNION SELECT DISTINCT machine FROM runs),"
            " last_end AS (SELECT DISTINCT ON (machine) machine, id, state, verdict, summary,"
            "   started_at, ended_at FROM runs WHERE state IN ('FAILED','ABORTED','INTERRUPTED')"
            "   OR (state = 'DONE' AND verdict IS NOT NULL) ORDER BY machine, started_at DESC),"
            " last_any AS (SELECT DISTINCT ON (machine) machine, id, state, started_at FROM runs"
            "   ORDER BY machine, started_at DESC)"
            " SELECT n.name, m.site, m.dialect, m.transport, e.id, e.state, e.verdict, e.summary,"
            "   e.started_at, e.ended_at, a.id, a.state, a.started_at,"
            "   (SELECT 1 FROM reports r WHERE r.run_id = e.id)"
            " FROM names n LEFT JOIN machines m ON m.name = n.name"
            " LEFT JOIN last_end e ON e.machine = n.name LEFT JOIN last_any a ON"
            " a.machine = n.name ORDER BY n.name")
        keys = ("machine", "site", "dialect", "transport", "run_id", "state", "verdict",
                "summary", "started_at", "ended_at", "current_run", "current_state",
                "current_started_at", "has_report")
        out = [dict(zip(keys, r, strict=True)) for r in rows]
        for d in out:
            # a run that ended without a verdict (failed, aborted) is an ERROR for the fleet
            if d["run_id"] and d["verdict"] is None:
                d["verdict"] = "ERROR"
            d["has_report"] = bool(d["has_report"])
        return out

    async def machine(self, name: str) -> dict[str, Any] | None:
        rows = await self._all("SELECT name, site, dialect, transport, limits FROM machines"
                               " WHERE name=%s", (name,))
        if not rows:
            return None
        r = rows[0]
        return {"name": r[0], "site": r[1], "dialect": r[2], "transport": r[3],
                "limits": json.loads(r[4])}

    async def trend(self, machine: str, since: float) -> list[dict[str, Any]]:
        """Runs with an analysis since ``since`` (Unix s), oldest first: the identified links
        (value, std, unit) and the verdict. Only the links object leaves the server."""
        rows = await self._all(
            "SELECT r.id, r.started_at, r.verdict, e.analysis"
            " FROM runs r JOIN estimates e ON e.run_id = r.id"
            " WHERE r.machine=%s AND r.started_at >= %s ORDER BY r.started_at",
            (machine, since))
        return [{"run_id": r[0], "started_at": r[1], "verdict": r[2] or "ERROR",
                 "links": analysis_part(r[3], "links") or {}} for r in rows]

    async def runs(self, machine: str, limit: int) -> list[dict[str, Any]]:
        """A machine's last ``limit`` runs, newest first, with whether a report exists, the
        temperature channels' summary of its analysis and its index scatter with the warnings
        (None without an analysis)."""
        rows = await self._all(
            "SELECT r.id, r.trigger, r.state, r.verdict, r.summary, r.started_at, r.ended_at,"
            " EXISTS (SELECT 1 FROM reports p WHERE p.run_id = r.id),"
            # the analysis' temperatures, index scatter and warnings: read below
            " (SELECT e.analysis FROM estimates e WHERE e.run_id = r.id),"
            # the drift checks name the baseline run; the reason a report failure
            " (SELECT v.checks FROM verdicts v WHERE v.run_id = r.id),"
            " (SELECT v.reasons FROM verdicts v WHERE v.run_id = r.id), r.reason,"
            # the report job (migration 10): being written, or why it was not
            " j.state, j.reason FROM runs r LEFT JOIN report_jobs j ON j.run_id = r.id"
            " WHERE r.machine=%s ORDER BY r.started_at DESC LIMIT %s", (machine, limit))
        keys = ("id", "trigger", "state", "verdict", "summary", "started_at", "ended_at",
                "has_report", "analysis", "checks", "reasons", "reason", "report_state",
                "report_error")
        out = []
        for r in rows:
            d = dict(zip(keys, r, strict=True))
            text = d.pop("analysis")
            d["temperatures"] = analysis_part(text, "temperatures")
            # the rotary axes' indexing repeatability and the warnings naming it
            d["index_scatter"] = None if text is None else {
                "index_scatter": analysis_part(text, "estimation", "index_scatter"),
                "warnings": analysis_part(text, "warnings")}
            out.append(d)
        return out

    async def report_job(self, run_id: str) -> tuple[str, str] | None:
        """(state, reason) of the run's report job (migration 10); None: it had none."""
        rows = await self._all("SELECT state, reason FROM report_jobs WHERE run_id=%s",
                               (run_id,))
        return (rows[0][0], rows[0][1]) if rows else None

    async def report_path(self, run_id: str) -> str | None:
        rows = await self._all("SELECT html_path FROM reports WHERE run_id=%s", (run_id,))
        return rows[0][0] if rows else None

    async def count_hits(self, run_id: str | None = None) -> int:
        if run_id is None:
            rows = await self._all("SELECT COUNT(*) FROM hits")
        else:
            rows = await self._all("SELECT COUNT(*) FROM hits WHERE run_id=%s", (run_id,))
        return int(rows[0][0])

    async def run_state(self, run_id: str) -> tuple[str, str | None] | None:
        rows = await self._all("SELECT state, verdict FROM runs WHERE id=%s", (run_id,))
        return (rows[0][0], rows[0][1]) if rows else None
