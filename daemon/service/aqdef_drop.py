"""The AQDEF file drop (``aqdef_dir`` in daemon.yaml, off when absent): after every
run of a machine that reached a verdict, ``<aqdef_dir>/<machine>_<run id>.dfq`` with that run's
value records (and a map job's map figures), for an SPC system watching the folder (qs-STAT's
upload, Solara …); ``rumba map --store`` drops ``<machine>_<map id>.dfq`` there too. Written
atomically, so a watcher never reads half a file; a failed write is logged, never the run's."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from daemon.machines.setup import MachineSetup
from daemon.reports.aqdef import write_aqdef
from daemon.store import map_results
from daemon.store.journal import Store, TrendPoint
from daemon.store.map_results import MapResult

log = logging.getLogger("rumba.aqdef")
IDLE_STATES = ("IDLE", "ABORTED", "INTERRUPTED", "FAILED")


class AqdefDrop:
    """One machine's listener: remembers the run under way, writes its file when it ends."""

    def __init__(self, directory: Path, setup: MachineSetup, store: Store) -> None:
        self.directory, self.setup, self.store = directory, setup, store
        self.busy_run: str | None = None
        self.written: list[Path] = []

    def on_status(self, st: dict[str, Any]) -> None:
        if st["state"] not in IDLE_STATES:
            self.busy_run = st["run_id"]
            return
        if self.busy_run is None:
            return
        run_id, self.busy_run = self.busy_run, None
        try:
            self.drop(run_id)
        except OSError as e:
            log.error("%s: AQDEF file of run %s not written in %s: %s", self.setup.name, run_id,
                      self.directory, e.strerror or e)

    def drop(self, run_id: str) -> Path | None:
        run, analysis = self.store.run(run_id), self.store.analysis(run_id)
        mapped = map_results.find(self.store, run_id)  # a map job's run: its map's figures
        checked = run.verdict is not None and analysis is not None
        if not checked and mapped is None:
            return None  # no verdict (aborted, failed …): nothing for the SPC chart
        runs = [TrendPoint(run.id, run.started_at, run.verdict, analysis)] if checked else []
        path = drop_file(self.directory, self.setup, run_id, runs,
                         [mapped] if mapped is not None else [])
        self.written.append(path)
        return path


def drop_file(directory: Path, setup: MachineSetup, ident: str, runs: list[TrendPoint],
              maps: list[MapResult]) -> Path:
    """``<directory>/<machine>_<ident>.dfq`` with these runs' and maps' value records."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{setup.name}_{ident}.dfq"
    write_aqdef(path, setup.name, runs, setup.tolerances, operator=setup.operator,
                artefact=setup.artefact.name, maps=maps)
    log.info("%s: AQDEF %s", setup.name, path)
    return path
