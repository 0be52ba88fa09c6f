"""Bulk reads and writes of the fleet store over a plain (synchronous) psycopg connection: a
history loaded in one transaction (machines, their runs and estimates, e.g. imported from
another system or seeded for a benchmark), and the hit count with duplicates told apart."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any


def load_history(conn: Any, machine: Sequence[Any], runs: Iterable[Sequence[Any]],
                 estimates: Iterable[Sequence[Any]]) -> None:
    """One machine row (``machines``' columns in order), its run rows (``runs``' columns) and
    their estimate rows (run id, analysis JSON), in the connection's current transaction
    (the caller commits)."""
    with conn.cursor() as cur:
        cur.execute("INSERT INTO machines VALUES (%s,%s,%s,%s,%s,%s)", tuple(machine))
        cur.executemany("INSERT INTO runs VALUES (%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s)",
                        [tuple(r) for r in runs])
        cur.executemany("INSERT INTO estimates VALUES (%s,%s)", [tuple(e) for e in estimates])


def analyze(conn: Any) -> None:
    """Refresh the planner's statistics after a bulk load."""
    conn.execute("ANALYZE")


def hit_counts(conn: Any) -> tuple[int, int]:
    """(hits stored, distinct (run, sequence) pairs among them): equal when nothing was
    written twice."""
    n, distinct = conn.execute("SELECT COUNT(*), COUNT(DISTINCT (run_id, seq)) FROM hits"
                               ).fetchone()
    return int(n), int(distinct)
