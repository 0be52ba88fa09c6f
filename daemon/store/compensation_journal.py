"""The ``compensations`` table of the run journal (migration 4 of daemon/store/schema.py): the
rows daemon/compensation/journal.py turns into compensation records, as the database holds
them (values as JSON text)."""

from __future__ import annotations

import sqlite3

from daemon.store.journal import Store

COLUMNS = ("id, machine, run_id, family, state, values_json, confirmed_by, reason, created_at,"
           " applied_at, verify_run_id, decision")


class DecisionTaken(Exception):
    """The journal refused a second write of the same run (its unique indexes, migration 5):
    another confirm got there first."""


def insert(store: Store, machine: str, run_id: str, family: str, state: str, values_json: str,
           confirmed_by: str, reason: str, created_at: float, applied_at: float | None) -> int:
    """A new row; its id."""
    cur = store.db.execute(
        "INSERT INTO compensations (machine, run_id, family, state, values_json, confirmed_by,"
        " reason, created_at, applied_at) VALUES (?,?,?,?,?,?,?,?,?)",
        (machine, run_id, family, state, values_json, confirmed_by, reason, created_at,
         applied_at))
    return int(cur.lastrowid or 0)


def update(store: Store, row_id: int, state: str | None, reason: str | None,
           confirmed_by: str | None, applied_at: float | None,
           verify_run_id: str | None) -> None:
    """Set the given fields of row ``row_id`` (None: left as it is)."""
    store.db.execute(
        "UPDATE compensations SET state=COALESCE(?, state), reason=COALESCE(?, reason),"
        " confirmed_by=COALESCE(?, confirmed_by), applied_at=COALESCE(?, applied_at),"
        " verify_run_id=COALESCE(?, verify_run_id) WHERE id=?",
        (state, reason, confirmed_by, applied_at, verify_run_id, row_id))


def row(store: Store, row_id: int) -> tuple | None:
    """Row ``row_id`` (``COLUMNS``), or None."""
    return store.db.execute(f"SELECT {COLUMNS} FROM compensations WHERE id=?",
                            (row_id,)).fetchone()


def rows(store: Store, machine: str | None) -> list[tuple]:
    """Every row (of ``machine``, None: of all machines), oldest first."""
    if machine is None:
        q = store.db.execute(f"SELECT {COLUMNS} FROM compensations ORDER BY id")
    else:
        q = store.db.execute(f"SELECT {COLUMNS} FROM compensations WHERE machine=? ORDER BY id",
                             (machine,))
    return list(q)


def decision_rows(store: Store, run_id: str) -> list[tuple]:
    """The rows of ``run_id`` that carry a decision number, in decision order."""
    q = store.db.execute(f"SELECT {COLUMNS} FROM compensations WHERE run_id=? AND decision IS "
                         "NOT NULL ORDER BY decision", (run_id,))
    return list(q)


def reserve_decision(store: Store, machine: str, run_id: str, family: str, values_json: str,
                     confirmed_by: str, reason: str, created_at: float, decision: int) -> int:
    """An 'applying' row holding decision ``decision`` of ``run_id`` (BEGIN IMMEDIATE: the
    unique indexes decide between concurrent writers); its id, else ``DecisionTaken``."""
    try:
        with store.transaction():
            taken = store.db.execute(
                "SELECT id, state FROM compensations WHERE run_id=? AND (state IN ('applied',"
                " 'applying') OR decision=?)", (run_id, decision)).fetchone()
            if taken is not None:
                raise DecisionTaken(f"run {run_id} is already {taken[1]} (journal #{taken[0]})")
            cur = store.db.execute(
                "INSERT INTO compensations (machine, run_id, family, state, values_json,"
                " confirmed_by, reason, created_at, decision) VALUES (?,?,?,?,?,?,?,?,?)",
                (machine, run_id, family, "applying", values_json, confirmed_by, reason,
                 created_at, decision))
    except sqlite3.IntegrityError as e:  # the index saw what the SELECT could not
        raise DecisionTaken(f"run {run_id}: decision {decision} is already journaled ({e})"
                            ) from None
    return int(cur.lastrowid or 0)


def finish(store: Store, row_id: int, state: str, values_json: str, reason: str,
           applied_at: float | None) -> None:
    """The 'applying' row gets its outcome; its decision number is kept only if applied."""
    store.db.execute(
        "UPDATE compensations SET state=?, values_json=?, reason=?, applied_at=?,"
        " decision=CASE WHEN ?='applied' THEN decision END WHERE id=?",
        (state, values_json, reason, applied_at, state, row_id))
