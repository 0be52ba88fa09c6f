"""The fleet store's rows the OPC UA results server reads (daemon/opcua/source.py): machines,
runs, a run's verdict and analysis, as PostgreSQL holds them (JSON as text)."""

from __future__ import annotations

from typing import Any

_RUN = ("SELECT id, machine, trigger, state, reason, plan, artefact, dialect, touch_total,"
        " started_at, ended_at, verdict, summary, imported FROM runs ")


async def machine_names(pg: Any) -> list[str]:
    """Every machine the store knows, declared or with runs, in name order."""
    rows = await pg._all("SELECT name FROM machines UNION SELECT DISTINCT machine"
                         " FROM runs ORDER BY 1")
    return [r[0] for r in rows]


async def run_rows(pg: Any, machine: str, limit: int) -> list[tuple]:
    """The machine's newest ``limit`` runs, newest first (columns as ``RunRow`` less the
    hit count)."""
    return await pg._all(_RUN + "WHERE machine=%s ORDER BY started_at DESC LIMIT %s",
                         (machine, limit))


async def run_row(pg: Any, run_id: str) -> tuple | None:
    """Run ``run_id``, or None."""
    rows = await pg._all(_RUN + "WHERE id=%s", (run_id,))
    return rows[0] if rows else None


async def verdict_row(pg: Any, run_id: str) -> tuple[str, str, str] | None:
    """(status, reasons JSON, checks JSON) of the run's verdict, or None."""
    rows = await pg._all("SELECT status, reasons, checks FROM verdicts WHERE run_id=%s",
                         (run_id,))
    return (rows[0][0], rows[0][1], rows[0][2]) if rows else None


async def analysis_json(pg: Any, run_id: str) -> str | None:
    """The run's stored analysis (JSON text), or None."""
    rows = await pg._all("SELECT analysis FROM estimates WHERE run_id=%s", (run_id,))
    return rows[0][0] if rows else None
