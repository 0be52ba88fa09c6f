"""The fleet store's map results: each daemon's ``map_results`` rows copied by its drainer
(idempotent, a map id owned by another machine refused), and read per machine as the journal's
are (``daemon/store/map_results.py``): the fleet page, the OPC UA results server on the fleet
store."""

from __future__ import annotations

import json
from typing import Any

import psycopg

from daemon.store.map_results import COLS, MapResult


async def write(conn: Any, row: tuple) -> bool:
    """Copy one map result (``COLS`` order); False when its id is another machine's (never
    merged). A row copied again (a lost acknowledgement, a map fitted again) replaces it."""
    sets = ", ".join(f"{c}=EXCLUDED.{c}" for c in COLS[1:])
    cur = await conn.execute(
        f"INSERT INTO map_results ({', '.join(COLS)}) VALUES ({', '.join(['%s'] * len(COLS))})"
        f" ON CONFLICT (id) DO UPDATE SET {sets} WHERE map_results.machine = EXCLUDED.machine"
        " RETURNING id", row)
    return await cur.fetchone() is not None


def _result(r: tuple) -> MapResult:
    d = dict(zip(COLS, r, strict=True))
    d["figures"] = json.loads(d["figures"])
    return MapResult(**d)


async def listed(conn: Any, machine: str, limit: int = 20) -> list[MapResult]:
    """A machine's map results, newest first."""
    try:
        cur = await conn.execute(f"SELECT {', '.join(COLS)} FROM map_results WHERE machine=%s"
                                 " ORDER BY created_at DESC LIMIT %s", (machine, limit))
    except psycopg.errors.UndefinedTable:
        return []  # a fleet store no daemon of this version has migrated yet: no maps
    return [_result(r) for r in await cur.fetchall()]


async def last(conn: Any, machine: str) -> MapResult | None:
    got = await listed(conn, machine, 1)
    return got[0] if got else None


async def latest_per_machine(conn: Any) -> dict[str, dict[str, Any]]:
    """Every machine's last map result (its figures and verdict), by machine: the fleet's
    overview of the linear axes."""
    cur = await conn.execute(f"SELECT DISTINCT ON (machine) {', '.join(COLS)} FROM map_results"
                             " ORDER BY machine, created_at DESC")
    return {m.machine: m.as_dict() for m in map(_result, await cur.fetchall())}
