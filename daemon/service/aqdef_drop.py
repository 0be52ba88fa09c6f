"""The AQDEF file drop (``aqdef_dir`` in daemon.yaml, off when absent): after every
run of a machine that reached a verdict, ``<aqdef_dir>/<machine>_<run id>.dfq`` with that run's
value records, for an SPC system watching the folder (qs-STAT's upload, Solara …). Written
atomically, so a watcher never reads half a file; a failed write is logged, never the run's."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from daemon.machines.setup import MachineSetup
from daemon.reports.aqdef import write_aqdef
from daemon.store.journal import Store, TrendPoint

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
        if run.verdict is None or analysis is None:
            return None  # no verdict (aborted, failed …): nothing for the SPC chart
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / f"{self.setup.name}_{run_id}.dfq"
        write_aqdef(path, self.setup.name, [TrendPoint(run.id, run.started_at, run.verdict,
                                                       analysis)],
                    self.setup.tolerances, operator=self.setup.operator,
                    artefact=self.setup.artefact.name)
        self.written.append(path)
        log.info("%s: AQDEF %s", self.setup.name, path)
        return path
