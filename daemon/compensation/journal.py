"""The compensation journal: every proposed, refused, applied or rolled-back change to a
controller's kinematic model, with old and new values and who confirmed it (table
``compensations`` of the run journal, migration 4 of daemon/store/schema.py)."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import Any, Literal

from daemon.store import compensation_journal as table
from daemon.store.compensation_journal import DecisionTaken
from daemon.store.journal import Store

State = Literal["applied", "applying", "rolled_back", "refused", "proposed"]
STATES: tuple[str, ...] = ("applied", "applying", "rolled_back", "refused", "proposed")
ROLLBACK_PREFIX = "rollback of compensation #"
__all__ = ["DecisionTaken"]  # raised by begin_apply, caught by its callers


@dataclass(frozen=True)
class ValueChange:
    """One controller value: ``old``/``new`` in the controller's unit (what is written),
    ``delta`` and ``u_expanded`` in the model's unit (mm or rad) of the change."""

    name: str
    address: str
    unit: str
    old: float
    new: float
    delta: float
    u_expanded: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "address": self.address, "unit": self.unit,
                "old": self.old, "new": self.new, "delta": self.delta,
                "u_expanded": self.u_expanded}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> ValueChange:
        return ValueChange(str(d["name"]), str(d["address"]), str(d.get("unit", "")),
                           float(d["old"]), float(d["new"]), float(d["delta"]),
                           float(d.get("u_expanded", 0.0)))

    def reversed(self) -> ValueChange:
        return ValueChange(self.name, self.address, self.unit, self.new, self.old, -self.delta,
                           self.u_expanded)


@dataclass(frozen=True)
class CompensationRow:
    id: int
    machine: str
    run_id: str
    family: str
    state: str
    values: tuple[ValueChange, ...]
    confirmed_by: str
    reason: str
    created_at: float
    applied_at: float | None
    verify_run_id: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    decision: int | None = None  # 1, 2, … : the n-th decision to write this run's values

    @property
    def is_rollback(self) -> bool:
        return self.reason.startswith(ROLLBACK_PREFIX)


def _row(r: tuple) -> CompensationRow:
    values = tuple(ValueChange.from_dict(d) for d in json.loads(r[5]))
    return CompensationRow(int(r[0]), r[1], r[2], r[3], r[4], values, r[6], r[7], float(r[8]),
                           None if r[9] is None else float(r[9]), r[10],
                           decision=None if r[11] is None else int(r[11]))


def _json(values: list[ValueChange]) -> str:
    return json.dumps([v.as_dict() for v in values])


def record(store: Store, machine: str, run_id: str, family: str, state: State,
           values: list[ValueChange], *, confirmed_by: str = "", reason: str = "",
           applied_at: float | None = None) -> int:
    """A new journal row; its id."""
    if state not in STATES:
        raise ValueError(f"compensation state {state!r} not one of {STATES}")
    return table.insert(store, machine, run_id, family, state, _json(values), confirmed_by,
                        reason, time.time(), applied_at)


def update(store: Store, row_id: int, *, state: State | None = None,
           reason: str | None = None, confirmed_by: str | None = None,
           applied_at: float | None = None, verify_run_id: str | None = None) -> None:
    table.update(store, row_id, state, reason, confirmed_by, applied_at, verify_run_id)


def get(store: Store, row_id: int) -> CompensationRow | None:
    r = table.row(store, row_id)
    return _row(r) if r else None


def rows(store: Store, machine: str | None = None) -> list[CompensationRow]:
    """Oldest first."""
    return [_row(r) for r in table.rows(store, machine)]


def written(store: Store, machine: str, before: float | None = None) -> list[CompensationRow]:
    """Rows whose values reached the controller (applied, rolled back, and the rollbacks
    themselves), in the order they were written; ``before``: written before that time."""
    out = [r for r in rows(store, machine) if r.applied_at is not None
           and r.state in ("applied", "rolled_back")
           and (before is None or r.applied_at < before)]
    return sorted(out, key=lambda r: (r.applied_at, r.id))


def current_values(store: Store, machine: str, before: float | None = None
                   ) -> dict[str, ValueChange]:
    """Per parameter name the last value written to the controller (its ``new``) and the
    change that wrote it; parameters never written are absent."""
    out: dict[str, ValueChange] = {}
    for r in written(store, machine, before):
        for v in r.values:
            out[v.name] = v
    return out


def last_applied(store: Store, machine: str) -> CompensationRow | None:
    """The most recent applied compensation not rolled back (what ``--rollback`` undoes)."""
    for r in reversed(written(store, machine)):
        if r.state == "applied":
            return r
    return None


def decisions(store: Store, run_id: str) -> list[CompensationRow]:
    """The decisions to write ``run_id``'s values (applied, being applied, rolled back), in
    order; rollbacks and refusals are not decisions."""
    return [_row(r) for r in table.decision_rows(store, run_id)]


def begin_apply(store: Store, machine: str, run_id: str, family: str,
                values: list[ValueChange], *, confirmed_by: str, decision: int) -> int:
    """Reserve decision ``decision`` of ``run_id`` as an 'applying' row before anything is
    written to the controller (BEGIN IMMEDIATE: the journal's unique indexes decide between
    concurrent writers); its id, else ``DecisionTaken``."""
    return table.reserve_decision(store, machine, run_id, family, _json(values), confirmed_by,
                                  "being written to the controller", time.time(), decision)


def finish_apply(store: Store, row_id: int, state: State, values: list[ValueChange],
                 reason: str, applied_at: float | None) -> None:
    """The 'applying' row becomes 'applied' (with the values written) or 'refused' (its
    decision number freed: nothing was written, a later confirm may try again)."""
    table.finish(store, row_id, state, _json(values), reason, applied_at)
