"""Where the OPC UA results server reads runs: a daemon's own SQLite journal, or the PostgreSQL
fleet store every daemon of a shop drains to (one endpoint for the shop).

Both answer the same seven questions, asynchronously (the fleet store is psycopg's async
connection; the journal's SQLite calls are quick and stay on the event loop as everywhere
in the daemon)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Protocol

from daemon.analysis.result import Analysis
from daemon.store import map_results, pg_maps, report_jobs
from daemon.store.journal import RunRow, Store, StoreError, validate_run_id
from daemon.store.map_results import MapResult


class ResultSource(Protocol):
    async def runs(self, machine: str, limit: int) -> list[RunRow]: ...
    async def run(self, run_id: str) -> RunRow | None: ...
    async def verdict(self, run_id: str) -> dict[str, Any] | None: ...
    async def analysis(self, run_id: str) -> Analysis | None: ...
    async def report(self, run_id: str) -> Path | None: ...
    async def report_job(self, run_id: str) -> tuple[str, str] | None: ...
    async def last_map(self, machine: str) -> MapResult | None: ...


class JournalSource:
    """A daemon's own journal."""

    def __init__(self, store: Store) -> None:
        self.store = store

    async def runs(self, machine: str, limit: int) -> list[RunRow]:
        return self.store.runs(machine, limit)

    async def run(self, run_id: str) -> RunRow | None:
        try:
            return self.store.run(run_id)
        except StoreError:  # unknown, or not a run id at all
            return None

    async def verdict(self, run_id: str) -> dict[str, Any] | None:
        return self.store.verdict(run_id)

    async def analysis(self, run_id: str) -> Analysis | None:
        return self.store.analysis(run_id)

    async def report(self, run_id: str) -> Path | None:
        rep = self.store.report(run_id)
        return rep[0] if rep else None

    async def report_job(self, run_id: str) -> tuple[str, str] | None:
        """(state, reason) of the run's report job (writing, written, failed); None: none."""
        try:
            job = report_jobs.get(self.store, run_id)
        except StoreError:
            return None
        return (job.state, job.reason) if job else None

    async def last_map(self, machine: str) -> MapResult | None:
        """The machine's last map result of the linear axes (None: none journaled)."""
        return map_results.last(self.store, machine)


_RUN = ("SELECT id, machine, trigger, state, reason, plan, artefact, dialect, touch_total,"
        " started_at, ended_at, verdict, summary, imported FROM runs ")


class FleetSource:
    """The PostgreSQL fleet store (``daemon.store.pg.PgStore``), read only."""

    def __init__(self, pg: Any) -> None:
        self.pg = pg

    @staticmethod
    def _row(r: tuple) -> RunRow:
        return RunRow(*r[:13], bool(r[13]), 0)

    async def machines(self) -> list[str]:
        rows = await self.pg._all("SELECT name FROM machines UNION SELECT DISTINCT machine"
                                  " FROM runs ORDER BY 1")
        return [r[0] for r in rows]

    async def runs(self, machine: str, limit: int) -> list[RunRow]:
        rows = await self.pg._all(_RUN + "WHERE machine=%s ORDER BY started_at DESC LIMIT %s",
                                  (machine, limit))
        return [self._row(r) for r in rows]

    async def run(self, run_id: str) -> RunRow | None:
        try:
            validate_run_id(run_id)
        except StoreError:
            return None
        rows = await self.pg._all(_RUN + "WHERE id=%s", (run_id,))
        return self._row(rows[0]) if rows else None

    async def verdict(self, run_id: str) -> dict[str, Any] | None:
        rows = await self.pg._all("SELECT status, reasons, checks FROM verdicts WHERE run_id=%s",
                                  (run_id,))
        if not rows:
            return None
        return {"status": rows[0][0], "reasons": json.loads(rows[0][1]),
                "checks": json.loads(rows[0][2])}

    async def analysis(self, run_id: str) -> Analysis | None:
        rows = await self.pg._all("SELECT analysis FROM estimates WHERE run_id=%s", (run_id,))
        return Analysis.from_json(json.loads(rows[0][0])) if rows else None

    async def report(self, run_id: str) -> Path | None:
        path = await self.pg.report_path(run_id)
        return Path(path) if path else None

    async def report_job(self, run_id: str) -> tuple[str, str] | None:
        try:
            validate_run_id(run_id)
        except StoreError:
            return None
        job = await self.pg.report_job(run_id)
        return (str(job[0]), str(job[1])) if job else None

    async def last_map(self, machine: str) -> MapResult | None:
        return await pg_maps.last(self.pg.conn, machine)
