"""A map job: one run that probes every placement of a map of the linear axes
(``contracts.map_job``), pauses between placements for the operator to move the artefact (a
Continue on the HMI or the control API, journaled with who pressed it), and ends with the map fit
of ``rumba map``, its JSON and each placement's probing log next to the run's reports.

Every program of the job is generated and checked against travel limits and keep-outs before
the first one moves the machine (each placement's own artefact), so a placement the machine
cannot reach is refused before the operator moves anything. Each placement's hits are journaled
the moment they arrive, as a verification run's, with the run's sequence numbers following one
another and the placement named in the hit's ``extra`` (``placement``: 1, 2 …; ``program_seq``:
its own program's sequence number). A stop at the prompt is a stop like any other: the run
ends ABORTED (or INTERRUPTED) with the hits of the placements done kept.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from contracts.linear_map import JobRecord, OperatorStep
from contracts.map_job import JobPlacement, MapJob
from contracts.messages import ProbeHit
from contracts.probing_log import write_log
from daemon.analysis import pipeline
from daemon.run.capture import RunCapture
from daemon.run.phases import END_READS, START_READS, Refused, RunFailed, State
from daemon.store.journal import StoreError
from daemon.store.map_results import record_map_result

log = logging.getLogger("rumba.session")

UNATTENDED = ("cnc", "rerun")  # triggers with nobody at the machine to move the artefact
JOBS = ("check", "map")


@dataclass
class Prompt:
    """The operator prompt of a map job between two placements."""

    placement: int  # 1-based: the placement to move the artefact to
    of: int
    name: str
    text: str
    since: float
    event: asyncio.Event

    def as_dict(self) -> dict[str, Any]:
        return {"placement": self.placement, "of": self.of, "name": self.name,
                "text": self.text, "since": self.since}


def check_job(setup: Any, job: str, trigger: str) -> None:
    """Refuse a job this machine has not, or a multi-placement map from a trigger with nobody
    at the machine (``Refused`` with the reason)."""
    if job not in JOBS:
        raise Refused(f"{setup.name}: job {job!r}: expected one of {', '.join(JOBS)}")
    if job != "map":
        return
    mj: MapJob | None = setup.map_job
    if mj is None:
        raise Refused(f"{setup.name}: no map job configured (daemon.yaml: map_job)")
    if trigger in UNATTENDED and len(mj.placements) > 1:
        raise Refused(f"{setup.name}: map job {mj.name} has {len(mj.placements)} placements "
                      f"and an operator must move the artefact between them: a {trigger} "
                      "start (nobody at the machine) cannot run it; start it from the HMI or "
                      "rumba verify --daemon --map")


class RunMap(RunCapture):
    """The session's map-job steps (``daemon.run.session.Session`` is one)."""

    reports_dir: Path
    job: str
    prompt: Prompt | None
    map_events: list[dict[str, Any]]
    map_result: dict[str, Any] | None  # the last map run's: {"status", "json"}
    _prepare: Callable[..., pipeline.Prepared]

    def continue_map(self, person: str) -> str:
        """The operator has moved the artefact (``person``: who said so): the job goes on.
        Returns the prompt answered; ``Refused`` when no prompt waits."""
        p = self.prompt
        if p is None or not self.busy or p.event.is_set():
            raise Refused(f"{self.setup.name}: no map placement waits for Continue")
        self.map_events.append({"placement": p.name, "prompted_at": p.since,
                                "continued_at": time.time(), "continued_by": person})
        log.info("%s %s: %s continues with placement %d (%s)", self.setup.name, self.run_id,
                 person, p.placement, p.name)
        p.event.set()
        return p.text

    async def _map_steps(self, run_id: str) -> None:
        """PREPARE every placement, then each placement streamed and journaled, the operator
        prompted between them; IDENTIFY: the map fit and its files."""
        job = self.setup.map_job
        assert job is not None
        self.map_events, self.map_result = [], None
        prepared = []
        for pl in job.placements:
            prepared.append(await asyncio.to_thread(self._prepare, self._placement_setup(pl),
                                                    run_id, None))
            self._raise_if_stopped()
        self.total = sum(p.job.touch_count for p in prepared)
        self.estimated_s = sum(p.estimated_s or 0.0 for p in prepared) or None
        self.store.set_state(run_id, "PREPARE", touch_total=self.total)
        self._enter(State.STREAM)
        self.step = START_READS
        await self.temps.start(run_id, self.clock.t_s())
        self.step = None
        by_placement: list[list[ProbeHit]] = []
        seq = 0
        for i, (pl, prog) in enumerate(zip(job.placements, prepared, strict=True)):
            if i > 0:
                await self._await_operator(run_id, i, pl, len(job.placements))
            hits = await self._capture(prog, _remap(i + 1, seq))
            seq += len(hits)
            by_placement.append(hits)
        self.step = END_READS
        await self.temps.end(run_id, self.clock.t_s())
        self._raise_if_stopped()
        self._enter(State.IDENTIFY)
        try:
            summary, self.map_result = await asyncio.to_thread(self._fit_map, run_id, job,
                                                               by_placement)
        except OSError as e:  # the hits are journaled: `rumba history --export` has them
            raise RunFailed(f"map: cannot write its files in {self.reports_dir}: "
                            f"{e.strerror or e}") from None
        try:  # journaled as a map result (history, HMI, fleet store, OPC UA, AQDEF)
            record_map_result(self.store, run_id, self.map_result["json"], None,
                              recorded_by="map job")
        except StoreError as e:
            raise RunFailed(f"map: written to {self.map_result['json']} but not journaled: "
                            f"{e}") from None
        self._raise_if_stopped()
        self._enter(State.IDLE, summary)

    def _placement_setup(self, pl: JobPlacement) -> Any:
        """The machine's setup with this placement's plan and artefact: the same generation
        and safety check as a verification run's, on nominal targets."""
        return replace(self.setup, plan=pl.plan, artefact=pl.artefact,
                       program_targets="nominal", reprobe_max=0)

    async def _await_operator(self, run_id: str, index: int, pl: JobPlacement, total: int
                              ) -> None:
        """Pause for the operator: the prompt published and journaled (the run's reason), the
        machine idle, until Continue; a stop meanwhile cancels this wait like any other."""
        text = pl.prompt(index, total)
        self.prompt = Prompt(index + 1, total, pl.name, text, time.time(), asyncio.Event())
        self.step = (f"between placements {index} and {index + 1} of {total}, waiting for the "
                     f"operator to move the artefact to {pl.name}")
        self.store.set_state(run_id, str(self.state), f"waiting for the operator: {text}")
        log.info("%s %s: %s", self.setup.name, run_id, text)
        waited = time.time()
        try:
            await self.prompt.event.wait()
        finally:
            self.prompt = None
        if self.first_hit_at is not None:  # the pace of the time left counts no waiting
            self.first_hit_at += time.time() - waited
        self._raise_if_stopped()
        self.step = None
        self.store.set_state(run_id, str(self.state), "")

    def _fit_map(self, run_id: str, job: MapJob, by_placement: list[list[ProbeHit]]
                 ) -> tuple[str, dict[str, Any]]:
        """The placements' probing logs and the map fit (``rumba map``'s), its JSON written
        next to the run's reports; the run's closing reason and its result for the status
        (the volumetric figure's status against the machine's limit, the JSON's path)."""
        from daemon.analysis.linear_map import fit_map_placements
        from identification.linmap.problem import MapError

        self.reports_dir.mkdir(parents=True, exist_ok=True)
        inputs = []
        for pl, hits in zip(job.placements, by_placement, strict=True):
            path = self.reports_dir / f"{run_id}.{pl.name}.csv"
            rows = [pipeline.hit_to_row(run_id, replace(h, seq=int(h.extra["program_seq"])),
                                        self.setup.machine) for h in hits if h.triggered]
            write_log(path, rows)
            inputs.append((str(path), str(pl.artefact_file)))
        tol = self.setup.tolerances
        try:
            run = fit_map_placements(
                self.setup.machine, self.setup.machine_file, self.setup.name, inputs,
                stylus_radius_mm=job.placements[0].plan.stylus_radius_mm,
                limit=tol.volumetric_max_um, limit_source=tol.sources.get("volumetric_max_um"),
                coverage_k=tol.coverage_k)
        except (MapError, ValueError) as e:
            raise RunFailed(f"map: {e} (the placements' hits are journaled and their logs "
                            f"written to {self.reports_dir})") from None
        doc = run.document.model_copy(update={"job": JobRecord(
            name=job.name, run_id=run_id, file=str(job.path),
            operator_steps=[OperatorStep(**e) for e in self.map_events])})
        out = self.reports_dir / f"{run_id}.map.json"
        out.write_text(json.dumps(doc.to_json(), indent=1, ensure_ascii=False) + "\n",
                       encoding="utf-8")
        fig = run.document.figures.volumetric_max_um
        judged = f", {fig.status} ({fig.limit})" if fig.status else ", not judged (no limit)"
        n = f"{len(inputs)} placement{'s' if len(inputs) > 1 else ''}"
        return (f"map of {n}: volumetric error max {fig.value_um:.2f} ± "
                f"{fig.u_um or 0:.2f} µm, RMS {run.document.figures.volumetric_rms_um:.2f} µm"
                f"{judged}; {out.name}"), {"status": fig.status, "json": str(out)}


def _remap(placement: int, seq_offset: int) -> Callable[[ProbeHit], ProbeHit]:
    def remap(hit: ProbeHit) -> ProbeHit:
        return replace(hit, seq=seq_offset + hit.seq,
                       extra={**hit.extra, "placement": float(placement),
                              "program_seq": float(hit.seq)})
    return remap
