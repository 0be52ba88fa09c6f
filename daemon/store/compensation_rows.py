"""The journal's rows the compensation path reads and writes: a run not ended, the stored
link view of a run, the state of a machine's compensation records."""

from __future__ import annotations

from daemon.store.journal import FINAL_STATES, Store


def unfinished_run(store: Store, machine: str) -> tuple[str, str] | None:
    """(run id, state) of the machine's newest run the journal shows as not ended, if any."""
    placeholders = ",".join("?" * len(FINAL_STATES))
    row = store.db.execute(
        f"SELECT id, state FROM runs WHERE machine=? AND state NOT IN ({placeholders}) "
        "ORDER BY started_at DESC LIMIT 1", (machine, *FINAL_STATES)).fetchone()
    return None if row is None else (row[0], row[1])


def save_link_view(store: Store, run_id: str, model_key: str, estimate_json: str,
                   plan_json: str, created_at: float) -> None:
    """A run's link estimate and compensation plan as computed for ``model_key``."""
    store.db.execute("INSERT OR REPLACE INTO link_estimates (run_id, model_key, estimate, plan,"
                     " created_at) VALUES (?, ?, ?, ?, ?)",
                     (run_id, model_key, estimate_json, plan_json, created_at))


def link_view(store: Store, run_id: str) -> tuple[str, str, str] | None:
    """(model key, estimate JSON, plan JSON) stored for ``run_id``, or None."""
    row = store.db.execute("SELECT model_key, estimate, plan FROM link_estimates WHERE"
                           " run_id=?", (run_id,)).fetchone()
    return None if row is None else (row[0], row[1], row[2])


def compensations_state(store: Store, machine: str) -> tuple[int, int, int, int]:
    """A fingerprint of the machine's compensation records: it changes whenever one is
    added, changes state or gets its verification run (a cache key, not a checksum)."""
    row = store.db.execute(
        "SELECT COUNT(*), COALESCE(MAX(id), 0), COALESCE(SUM(id * LENGTH(state)), 0),"
        " COUNT(verify_run_id) FROM compensations WHERE machine=?", (machine,)).fetchone()
    return (int(row[0]), int(row[1]), int(row[2]), int(row[3]))
