"""Re-probing of faulty ball visits after the program: which visits the outlier test names in
the captured hits, the checked program that probes their poses again, and the identity each
of its hits gets in the journal.

A probing cycle on a CNC measures a feature again when a result looks wrong; a program that is
loaded whole (OPC UA, LinuxCNC, a Heidenhain file) cannot wait inside itself for the daemon's
statistics, so the repair runs after it: the poses of the faulty visits, in plan order, become
one more program through the same generation and safety check as the run's (all balls of the
pose: the program is built and checked per pose and artefact, and the re-probed pose's other
balls show whether the re-indexation reproduces the first visit). Its hits are journaled as the
visits they re-measure with repeat ``100 · round + repeat`` (``identification.outliers``), after
the run's last sequence number: both visits stay in the journal and the analysis uses the clean
one.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace

from contracts.messages import ProbeHit
from daemon.analysis import pipeline
from daemon.analysis import result as analysis_result
from daemon.analysis.touch_centres import describe_outlier, rows_to_centres, screen_centres
from daemon.machines.setup import MachineSetup
from identification.outliers import reprobe_repeat, split_repeat


@dataclass(frozen=True)
class Reprobe:
    """One re-probe round: the checked program and how its hits are named in the run."""

    prepared: pipeline.Prepared  # its touch table carries the program's own identities
    round: int
    slots: tuple[tuple[int, int], ...]  # program pose index → (repeat re-measured, plan pose)
    seq_offset: int  # the run's last sequence number before this program
    faults: tuple[str, ...]  # the visits that asked for it, as messages name them

    def remap(self, hit: ProbeHit) -> ProbeHit:
        """A hit of this program as the run journals it: the plan's pose, the re-probe's
        repeat, a sequence number after the run's (the program's own kept in ``extra``); its
        ``t_s`` is already on the run's clock (the session hands this program the run's
        ``contracts.jobs.RunClock``), after the plan's hits."""
        repeat, pose = self.slots[hit.pose]
        return replace(hit, seq=self.seq_offset + hit.seq, pose=pose,
                       repeat=reprobe_repeat(repeat, self.round),
                       extra={**hit.extra, "program_seq": float(hit.seq)})


def faulty_visits(setup: MachineSetup, hits: Sequence[ProbeHit], run_id: str
                  ) -> list[analysis_result.Outlier]:
    """The visits of ``hits`` the outlier test names and no clean re-probe has replaced (the
    same test IDENTIFY runs: ``daemon.analysis.touch_centres.screen_centres``). Hits that cannot be
    fitted give none here: IDENTIFY reports why."""
    rows = [pipeline.hit_to_row(run_id, h, setup.machine) for h in hits if h.triggered]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = rows_to_centres(rows, setup.artefact, setup.plan.stylus_radius_mm,
                                   source=f"run {run_id}")
        _, parts = screen_centres(setup.machine, setup.artefact, data)
    except (ValueError, pipeline.PipelineError):
        return []
    if parts is None:
        return []
    return [analysis_result.Outlier.from_json(o) for o in parts["outliers"]
            if o["status"] == "unrepaired"]


def plan_reprobe(setup: MachineSetup, hits: Sequence[ProbeHit], run_id: str, round_: int,
                 last_good: analysis_result.Analysis | None = None) -> Reprobe | None:
    """Round ``round_`` (1, 2 …): the program probing again every pose with a faulty visit in
    ``hits``, or None when there is none. ``pipeline.PipelineError`` when the program cannot
    be generated or is refused by the safety check."""
    faults = faulty_visits(setup, hits, run_id)
    if not faults:
        return None
    slots = sorted({(int(split_repeat(o.repeat)[0]), o.pose) for o in faults})
    plan = setup.plan.model_copy(update={"poses": [setup.plan.poses[p] for _, p in slots],
                                         "repeats": 1, "drift_check": False})
    prepared = pipeline.prepare(replace(setup, plan=plan), f"{run_id}-rp{round_}", last_good)
    return Reprobe(prepared, round_, tuple(slots), max((h.seq for h in hits), default=0),
                   tuple(describe_outlier(o.ball, o.pose, o.repeat, o.touch, o.size_um or 0.0)
                         for o in faults))
