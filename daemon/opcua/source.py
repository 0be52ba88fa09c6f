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
from daemon.store import map_results, pg_maps, pg_results, report_jobs
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


class FleetSource:
    """The PostgreSQL fleet store (``daemon.store.pg.PgStore``), read only."""

    def __init__(self, pg: Any) -> None:
        self.pg = pg

    @staticmethod
    def _row(r: tuple) -> RunRow:
        return RunRow(*r[:13], bool(r[13]), 0)

    async def machines(self) -> list[str]:
        return await pg_results.machine_names(self.pg)

    async def runs(self, machine: str, limit: int) -> list[RunRow]:
        return [self._row(r) for r in await pg_results.run_rows(self.pg, machine, limit)]

    async def run(self, run_id: str) -> RunRow | None:
        try:
            validate_run_id(run_id)
        except StoreError:
            return None
        row = await pg_results.run_row(self.pg, run_id)
        return self._row(row) if row else None

    async def verdict(self, run_id: str) -> dict[str, Any] | None:
        row = await pg_results.verdict_row(self.pg, run_id)
        if row is None:
            return None
        return {"status": row[0], "reasons": json.loads(row[1]), "checks": json.loads(row[2])}

    async def analysis(self, run_id: str) -> Analysis | None:
        text = await pg_results.analysis_json(self.pg, run_id)
        return Analysis.from_json(json.loads(text)) if text is not None else None

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
