"""The HMI's audit trail: every start, abort, compensation confirm and rollback a person asked
for, with the person's name and role, how they were signed in and what came of it."""

from __future__ import annotations

import time
from dataclasses import dataclass

from daemon.store.journal import Store

ACTIONS = ("start", "abort", "confirm", "rollback", "continue")


@dataclass(frozen=True)
class Action:
    """One row of ``hmi_actions``."""

    id: int
    at: float
    machine: str
    run_id: str
    action: str
    person: str
    role: str
    via: str  # "password" (an account), "token-login", "bearer"
    outcome: str  # "ok", or "refused: <why>"
    detail: str


def record_action(store: Store, machine: str, action: str, person: str, role: str, via: str,
                  outcome: str, *, run_id: str = "", detail: str = "") -> int:
    """Journal one action now (its own transaction); the row id."""
    if action not in ACTIONS:
        raise ValueError(f"unknown HMI action {action!r}")
    cur = store.db.execute(
        "INSERT INTO hmi_actions (at, machine, run_id, action, person, role, via, outcome,"
        " detail) VALUES (?,?,?,?,?,?,?,?,?)",
        (time.time(), machine, run_id, action, person, role, via, outcome[:500], detail[:500]))
    return int(cur.lastrowid or 0)


def actions(store: Store, machine: str | None = None, limit: int = 100) -> list[Action]:
    """The newest actions first (one machine's, or all)."""
    where, args = ("WHERE machine=?", (machine,)) if machine else ("", ())
    rows = store.db.execute(
        "SELECT id, at, machine, run_id, action, person, role, via, outcome, detail FROM"
        f" hmi_actions {where} ORDER BY id DESC LIMIT ?", (*args, limit))
    return [Action(*r) for r in rows]
