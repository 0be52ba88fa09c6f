"""The journal's temperature readings: each committed on arrival in its own
transaction, as a hit is (``Store.journal_hit``), so a ``kill -9`` loses none already read."""

from __future__ import annotations

import time

from contracts.temperatures import TemperatureReading
from daemon.store.journal import Store, validate_run_id


def journal_temperature(store: Store, run_id: str, r: TemperatureReading) -> None:
    """Commit one reading (autocommit: its own transaction); numbered in arrival order."""
    validate_run_id(run_id)
    store.db.execute(
        "INSERT INTO temperatures (run_id, seq, channel, at, pose, t_s, value_c, error,"
        " received_at, reprobe_round) SELECT ?, COALESCE(MAX(seq), 0) + 1, ?, ?, ?, ?, ?, ?,"
        " ?, ? FROM temperatures WHERE run_id=?",
        (run_id, r.channel, r.at, r.pose, r.t_s, r.value_c, r.error, time.time(),
         r.reprobe_round, run_id))


def temperatures(store: Store, run_id: str) -> list[TemperatureReading]:
    """The run's readings in arrival order."""
    validate_run_id(run_id)
    rows = store.db.execute(
        "SELECT channel, at, pose, t_s, value_c, error, reprobe_round FROM temperatures"
        " WHERE run_id=?"
        " ORDER BY seq", (run_id,))
    return [TemperatureReading(*row) for row in rows]
