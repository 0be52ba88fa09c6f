"""Probing-log CSV in and out of the journal: export a run, import a log as a new run."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

from contracts.messages import ProbeHit
from contracts.probing_log import LogRow, read_log, write_log
from daemon.analysis.pipeline import hit_to_row, row_to_hit
from daemon.store.journal import Store, StoreError, validate_run_id


def export_csv(store: Store, run_id: str, path: Path | str, machine: Any) -> int:
    """Write the journaled hits of ``run_id`` as a probing log (DESIGN.md contract); returns
    the number of rows. Untriggered hits are left out (the log holds latched touches only)."""
    store.run(run_id)  # raises StoreError for an unknown run
    rows = [hit_to_row(run_id, h, machine) for h in store.hits(run_id) if h.triggered]
    write_log(path, rows)
    return len(rows)


def read_import(store: Store, path: Path | str, artefact: Any) -> tuple[str, list[LogRow]]:
    """Read and check a probing log for import, writing nothing: (its run id, its rows). One
    run per file, with a safe run id that the journal does not have yet."""
    rows = read_log(path, artefact)
    run_ids = sorted({r.run_id for r in rows})
    if len(run_ids) != 1:
        raise StoreError(f"{path}: contains runs {run_ids}; import one run at a time")
    run_id = validate_run_id(run_ids[0], f"{path}: column run_id")
    if store.db.execute("SELECT 1 FROM runs WHERE id=?", (run_id,)).fetchone():
        raise StoreError(f"{path}: run {run_id} is already in the journal")
    return run_id, rows


def journal_import(store: Store, run_id: str, hits: list[ProbeHit], machine_name: str,
                   artefact: Any) -> int:
    """Journal imported hits as a new run (inside the caller's ``store.transaction()`` when
    more is to be committed with them); returns the number of hits."""
    with store.transaction():
        store.new_run(run_id, machine_name, "import", artefact=getattr(artefact, "name", ""),
                      touch_total=len(hits), state="IMPORTED", imported=True)
        return store.journal_hits(run_id, hits)


def import_csv(store: Store, path: Path | str, machine_name: str, machine: Any,
               artefact: Any) -> tuple[str, int]:
    """Journal a probing log as a new (imported) run of ``machine_name``; returns (run id, rows).
    The log's run id is kept (refused if the journal has it already). All or nothing: a row
    the journal refuses leaves no trace of the run."""
    run_id, rows = read_import(store, path, artefact)
    hits = [row_to_hit(r, machine) for r in rows]
    try:
        return run_id, journal_import(store, run_id, hits, machine_name, artefact)
    except sqlite3.IntegrityError as e:
        raise StoreError(f"{path}: the journal refuses run {run_id}: {e} (two rows with the "
                         "same seq?)") from None
