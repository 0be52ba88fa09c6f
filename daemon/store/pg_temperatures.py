"""The fleet store's temperature readings: each run's raw readings copied with its
rows (journal order, idempotent), and per run one channel's readings beside the run's links —
what the fleet page's link-against-temperature view fits (daemon/analysis/temperature_trend.py).
"""

from __future__ import annotations

from typing import Any

from daemon.store.stored_json import analysis_part

TEMP_COLS = ("run_id", "seq", "channel", "at", "pose", "t_s", "value_c", "error", "received_at",
             "reprobe_round")


async def insert(cur: Any, rows: list[tuple]) -> None:
    """Copy readings (``TEMP_COLS`` order) in the caller's transaction; one already there (a
    batch copied twice after a lost acknowledgement) stays as it was."""
    if rows:
        await cur.executemany(
            f"INSERT INTO temperatures ({', '.join(TEMP_COLS)}) VALUES "
            f"({', '.join(['%s'] * len(TEMP_COLS))}) ON CONFLICT (run_id, seq) DO NOTHING",
            rows)


async def channels(conn: Any, machine: str) -> list[str]:
    """The channels with at least one reading in the machine's runs, by name."""
    cur = await conn.execute(
        "SELECT DISTINCT t.channel FROM temperatures t JOIN runs r ON r.id = t.run_id"
        " WHERE r.machine=%s ORDER BY 1", (machine,))
    return [r[0] for r in await cur.fetchall()]


async def readings(conn: Any, machine: str, since: float, channel: str
                   ) -> list[dict[str, Any]]:
    """Runs since ``since`` with an analysis and a reading of ``channel``, oldest first: the
    links object, the values read at each pose, the run's start and end value as
    ``contracts.temperatures.run_ends`` picks them (the plan program's first start read; the
    last program's end, NULL when it was not read)."""
    cur = await conn.execute(
        "SELECT r.id, r.started_at, r.verdict, e.analysis,"
        " array_agg(t.value_c ORDER BY t.seq) FILTER (WHERE t.at = 'pose'"
        "   AND t.value_c IS NOT NULL),"
        " (array_agg(t.value_c ORDER BY t.seq) FILTER (WHERE t.at = 'start'"
        "   AND t.reprobe_round = 0 AND t.value_c IS NOT NULL))[1],"
        " (array_agg(t.value_c ORDER BY t.reprobe_round DESC, t.seq DESC)"
        "   FILTER (WHERE t.at = 'end'))[1],"
        " COUNT(*), COUNT(t.value_c)"
        " FROM runs r JOIN estimates e ON e.run_id = r.id"
        " JOIN temperatures t ON t.run_id = r.id AND t.channel = %s"
        " WHERE r.machine = %s AND r.started_at >= %s"
        " GROUP BY r.id, r.started_at, r.verdict, e.analysis ORDER BY r.started_at",
        (channel, machine, since))
    keys = ("run_id", "started_at", "verdict", "links", "pose_c", "start_c", "end_c",
            "readings", "read")
    out = []
    for r in await cur.fetchall():
        d = dict(zip(keys, r, strict=True))
        d["links"] = analysis_part(d["links"], "links")  # NaN-tolerant (not jsonb)
        out.append(d)
    return out
