"""Before and after of a compensation, in the report of the run that verifies it: the first run
started after an applied compensation shows the values written and, per link, the compensating
run's estimate beside its own (identified against the compensated controller model)."""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass
from typing import Any

from contracts.yaml_files import ConfigError
from daemon.analysis.judge import volumetric_max_um
from daemon.analysis.result import Analysis
from daemon.compensation import journal as cj
from daemon.compensation.baseline_check import objections
from daemon.compensation.listing import listing_json, row_listing
from daemon.compensation.model import spec_of
from daemon.machines.setup import MachineSetup
from daemon.store import baselines
from daemon.store.journal import RunRow, Store


@dataclass(frozen=True)
class LinkBeforeAfter:
    name: str
    unit: str  # "um" | "urad"
    before: float
    u_before: float  # standard uncertainty (k = 1)
    after: float
    u_after: float


@dataclass(frozen=True)
class CompensationView:
    row_id: int
    source_run: str  # the run the compensation was computed from
    confirmed_by: str
    applied_at: float
    values: tuple[cj.ValueChange, ...]
    links: tuple[LinkBeforeAfter, ...]
    distortion_before_um: float | None  # largest volumetric distortion (nominal + setup)
    distortion_after_um: float | None
    # what the compensation put on the controller, address by address, as the program wrote
    # it (``compensation.listing``); empty when the machine file no longer names the values
    writes: tuple[dict[str, Any], ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {"journal_row": self.row_id, "source_run": self.source_run,
                "confirmed_by": self.confirmed_by, "applied_at": self.applied_at,
                "values": [v.as_dict() for v in self.values],
                "links": [asdict(v) for v in self.links],
                "distortion_before_um": self.distortion_before_um,
                "distortion_after_um": self.distortion_after_um,
                "writes": list(self.writes)}


def verification_of(store: Store, run: RunRow, analysis: Analysis,
                    setup: MachineSetup | None = None) -> CompensationView | None:
    """The compensation ``run`` verifies, or None: the machine's last applied compensation
    (not rolled back) when ``run`` started after it and no other run verified it yet. Records
    ``run`` as its verification run in the journal and proposes it as the drift baseline.
    ``setup``: its controller_kinematics section gives the addresses as written."""
    last = cj.last_applied(store, run.machine)
    if last is None or last.applied_at is None or run.started_at < last.applied_at:
        return None
    if last.verify_run_id not in (None, run.id):
        return None
    source = store.analysis(last.run_id)
    if source is None:
        return None
    if last.verify_run_id is None:
        cj.update(store, last.id, verify_run_id=run.id)
        # the verification run is proposed as the drift baseline; a person confirms
        if not objections(store, run.machine, run.id):  # never a FAILed one
            baselines.propose(store, run.machine, run.id,
                              f"verification run of compensation #{last.id} (run "
                              f"{last.run_id})")
    links = tuple(LinkBeforeAfter(n, v.unit, v.value, v.std, analysis.links[n].value,
                                  analysis.links[n].std)
                  for n, v in sorted(source.links.items()) if n in analysis.links)
    writes: tuple[dict[str, Any], ...] = ()
    if setup is not None:
        with contextlib.suppress(ConfigError):
            spec = spec_of(setup)
            writes = tuple(listing_json(row_listing(spec, last))) if spec else ()
    return CompensationView(last.id, last.run_id, last.confirmed_by, last.applied_at,
                            last.values, links, volumetric_max_um(source),
                            volumetric_max_um(analysis), writes)
