"""Each machine's drift baseline: a run a person accepted, proposed or confirmed, journaled."""

# Drift is judged against a run a person chose, not "the last PASS run" (a
# machine that stays in WARN lost its drift check). Every decision is a row of ``baselines``
# (migration 8) with who and when: the machine's baseline is its newest ``confirmed`` row; a
# ``proposed`` row (the verification run after a compensation) waits for a person to confirm
# it and changes nothing until then.

from __future__ import annotations

import time
from dataclasses import dataclass

from daemon.analysis.result import Analysis
from daemon.store.journal import Store, StoreError, validate_run_id

STATES = ("proposed", "confirmed")


@dataclass(frozen=True)
class Baseline:
    """One row of ``baselines``: a run proposed or confirmed as a machine's drift baseline."""

    id: int
    machine: str
    run_id: str
    state: str  # proposed | confirmed
    by: str  # the person (or "rumba" for a proposal the daemon made)
    at: float
    note: str
    run_started_at: float = 0.0

    def describe(self) -> str:
        """"run R of 2026-03-14 06:02 (confirmed by Anna Berg on 2026-03-14 07:10)"."""
        when = time.strftime("%Y-%m-%d %H:%M", time.localtime(self.run_started_at))
        said = time.strftime("%Y-%m-%d %H:%M", time.localtime(self.at))
        return f"run {self.run_id} of {when} ({self.state} by {self.by} on {said})"

    def as_dict(self) -> dict[str, object]:
        return {"run_id": self.run_id, "state": self.state, "by": self.by, "at": self.at,
                "note": self.note, "run_started_at": self.run_started_at,
                "text": self.describe()}


def _row(store: Store, where: str, args: tuple) -> Baseline | None:
    row = store.db.execute(
        "SELECT b.id, b.machine, b.run_id, b.state, b.by_person, b.at, b.note, r.started_at"
        " FROM baselines b JOIN runs r ON r.id = b.run_id " + where
        + " ORDER BY b.id DESC LIMIT 1", args).fetchone()
    return Baseline(*row) if row else None


def current(store: Store, machine: str) -> Baseline | None:
    """The machine's baseline: its newest confirmed row; None when nobody confirmed one."""
    return _row(store, "WHERE b.machine=? AND b.state='confirmed'", (machine,))


def pending(store: Store, machine: str) -> Baseline | None:
    """A proposal newer than the current baseline, waiting for a person; None otherwise."""
    cur = current(store, machine)
    return _row(store, "WHERE b.machine=? AND b.state='proposed' AND b.id > ?",
                (machine, cur.id if cur else 0))


def history(store: Store, machine: str, limit: int = 20) -> list[Baseline]:
    rows = store.db.execute(
        "SELECT b.id, b.machine, b.run_id, b.state, b.by_person, b.at, b.note, r.started_at"
        " FROM baselines b JOIN runs r ON r.id = b.run_id WHERE b.machine=?"
        " ORDER BY b.id DESC LIMIT ?", (machine, limit)).fetchall()
    return [Baseline(*r) for r in rows]


def _check_run(store: Store, machine: str, run_id: str, *, finished: bool = True) -> None:
    """A baseline is a finished run of this machine with an analysis and a verdict that
    trusts the measurement (not ERROR); a proposal may be made while the run is reported
    (``finished`` False: judged, not yet DONE)."""
    validate_run_id(run_id)
    try:
        run = store.run(run_id)
    except (StoreError, KeyError):
        raise StoreError(f"run {run_id} is not in the journal") from None
    if run.machine != machine:
        raise StoreError(f"run {run_id} is of machine {run.machine}, not {machine}")
    if (finished and run.state != "DONE") or store.analysis(run_id) is None:
        raise StoreError(f"run {run_id} has no result (state {run.state}): only a finished, "
                         "identified run can be a baseline")
    if run.verdict == "ERROR":
        raise StoreError(f"run {run_id}: its verdict is ERROR (measurement not trusted), it "
                         "cannot be a baseline")


def _insert(store: Store, machine: str, run_id: str, state: str, by: str, note: str) -> int:
    cur = store.db.execute(
        "INSERT INTO baselines (machine, run_id, state, by_person, at, note) VALUES"
        " (?,?,?,?,?,?)", (machine, run_id, state, by, time.time(), note[:500]))
    return int(cur.lastrowid or 0)


def confirm(store: Store, machine: str, run_id: str, by: str, note: str = "") -> Baseline:
    """A person sets (or confirms the proposed) ``run_id`` as ``machine``'s baseline.
    ``by`` must be a person's name, checked by the caller (``compensation.names``)."""
    _check_run(store, machine, run_id)
    _insert(store, machine, run_id, "confirmed", by, note)
    got = current(store, machine)
    assert got is not None
    return got


def propose(store: Store, machine: str, run_id: str, note: str) -> Baseline | None:
    """The daemon proposes ``run_id`` (a compensation's verification run); a person confirms
    it. Nothing when the run cannot be a baseline or is the baseline already."""
    try:
        _check_run(store, machine, run_id, finished=False)
    except StoreError:
        return None
    cur = current(store, machine)
    if cur is not None and cur.run_id == run_id:
        return None
    _insert(store, machine, run_id, "proposed", "rumba", note)
    return pending(store, machine)


def reference(store: Store, machine: str, before: str | None = None
              ) -> tuple[Baseline, Analysis] | None:
    """The baseline of ``machine`` and its analysis (the drift reference of a run), None when
    there is none; never the run ``before`` itself."""
    b = current(store, machine)
    if b is None or b.run_id == before:
        return None
    a = store.analysis(b.run_id)
    return (b, a) if a is not None else None
