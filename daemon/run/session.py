"""One verification session per machine: the run state machine of DESIGN.md.

IDLE → PREPARE → STREAM → CAPTURE → IDENTIFY → JUDGE → WRITE-BACK → IDLE, or ABORTED /
INTERRUPTED / FAILED with the phase and the cause (their meaning: run/phases.py READY_STATES);
the report is written after the run's end, in a worker (run/report_job.py).
The capture (run/capture.py) and the stopping and write-back steps (run/ending.py) are the
session's own, in modules of their own. Each step is handed the previous step's result and the
journal records it (raw hits before anything else looks at them); a probe that does not
trigger, a hit that does not match the program, a silent controller or a lost link stop the
run, and the next run reconnects first; a second trigger during a run is refused with a reason;
abort works from any source.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from contracts.jobs import RunClock, Verdict
from contracts.messages import ProbeHit
from daemon.analysis import pipeline
from daemon.analysis.figures import figures_json, run_figures
from daemon.analysis.judge import Judgement, judge
from daemon.analysis.result import Analysis
from daemon.machines.setup import MachineSetup
from daemon.reports.index_scatter import index_scatter_lines
from daemon.reports.temperatures import temperature_lines
from daemon.run import lease as run_lease
from daemon.run import report_job
from daemon.run.ending import ABORT_TIMEOUT_S, WRITE_BACK_TIMEOUT_S, await_run
from daemon.run.map_job import RunMap, check_job
from daemon.run.phases import (
    END_READS,
    START_READS,
    ControllerSilent,
    Refused,
    RunFailed,
    State,
    new_run_id,
)
from daemon.run.temperatures import TemperatureRecorder
from daemon.store import baselines
from daemon.store.journal import Store
from daemon.store.machine_lock import Lease
from drivers.base import CncLink, ControllerAborted, ControllerAlarm, LinkError
from drivers.hits import MalformedResult
from drivers.retry import with_backoff

log = logging.getLogger("rumba.session")

__all__ = ["ABORT_TIMEOUT_S", "RECONNECT_TIMEOUT_S", "WRITE_BACK_TIMEOUT_S", "Refused",
           "Session", "State", "new_run_id"]

RECONNECT_TIMEOUT_S = 3600.0 * 24  # keep trying; the HMI shows the link as down meanwhile
# a report renders in seconds (2.2 s of CPU, more on a loaded shop PC); a stop waits this long
# for it before journaling it "not written", within the unit's stop timeout (TimeoutStopSec=30s,
# config/systemd/rumba.service) with the other steps of the stop
REPORT_STOP_WAIT_S = 15.0


class Session(RunMap):
    """Runs verification programs on one machine through one link, one at a time."""

    def __init__(self, setup: MachineSetup, link: CncLink, store: Store, reports_dir: Path,
                 *, analyse: Callable[..., pipeline.RunAnalysis] = pipeline.analyse,
                 prepare: Callable[..., pipeline.Prepared] = pipeline.prepare,
                 after_run: Callable[[Session, str], object] | None = None) -> None:
        super().__init__(setup, store)
        self.after_run = after_run  # e.g. unattended compensation (daemon.run.unattended)
        self.link = link
        self.reports_dir = Path(reports_dir)
        self._analyse = analyse
        self._prepare = prepare
        self._task: asyncio.Task | None = None
        self._report_task: asyncio.Task | None = None  # the last run's report (report_job)
        self._abort_reason: str | None = None
        self._abort_state = State.ABORTED  # INTERRUPTED when the daemon stops under the run
        self.lease: Lease | None = None  # the machine lock of the current run (run/lease.py)
        self._controller_dirty = False  # a stop could not reach the controller
        self.baseline: baselines.Baseline | None = None  # the current run's drift baseline
        self.following: str | None = None  # the last run's follow-up under way (_follow_up)
        self.closing = False  # shutdown under way: no run starts
        self._follow_task: asyncio.Task | None = None
        self.temps = TemperatureRecorder(setup.name, setup.temperatures, link, store,
                                         str(getattr(setup.link, "transport", "")))
        self.clock = RunClock()  # the current run's touch and temperature times
        self.job = "check"  # the current run's job: "check" (the plan) or "map" (run/map_job.py)
        self.prompt = None  # a map job's operator prompt between placements
        self.map_events: list[dict[str, Any]] = []
        self.map_result: dict[str, Any] | None = None
        link.on_step = self._machine_step  # what the run waits for at the machine (NC start)

    def _machine_step(self, text: str | None) -> None:
        """The link says what the run waits for at the machine ("waiting for NC start …",
        None once the program runs): the status's step while the run is busy."""
        if self.busy:
            self.step = text

    async def reconnect(self) -> None:
        """Close the link and connect it again with backoff; the status shows it up again."""
        with contextlib.suppress(Exception):
            await self.link.close()
        await with_backoff(self.link.connect, what=f"{self.setup.name} controller",
                           timeout_s=RECONNECT_TIMEOUT_S)
        self.set_link_ok(True)

    # ----------------------------------------------------------------------------- commands
    def start(self, trigger: str, started_by: str = "", job: str = "check") -> str:
        """Start a run now (returns its id) or raise ``Refused`` with the reason;
        ``started_by``: the person (an HMI account) who asked, journaled with the run;
        ``job``: the verification ("check") or the machine's map job ("map")."""
        check_job(self.setup, job, trigger)
        if trigger not in ("cli", "rerun") and not getattr(self.setup.triggers, trigger, True):
            raise Refused(f"{self.setup.name}: trigger '{trigger}' is disabled in the config")
        if self.busy:
            raise Refused(f"{self.setup.name}: run {self.run_id} in progress "
                          f"(state {self.state}, started by {self.trigger}); "
                          f"{trigger} request refused")
        if self.closing:
            raise Refused(f"{self.setup.name}: the daemon is stopping; {trigger} request "
                          "refused")
        if self.following is not None and trigger != "rerun":  # its lease is the run's
            raise Refused(f"{self.setup.name}: {self.following}; {trigger} request refused")
        # a compensation being written refuses the run; the run holds the machine to its end
        lease = self.lease = run_lease.take(self.lease, self.store.path, self.setup.name, trigger)
        self.run_id = new_run_id()
        lease.describe(f"run {self.run_id} (started by {started_by or trigger})")
        self.trigger, self.started_by, self.job = trigger, started_by, job
        self.done, self.total = 0, 0
        self.started_at, self.first_hit_at, self.estimated_s = time.time(), None, None
        self.clock = RunClock()  # started by the link with the run's first program
        self.verdict, self.reason, self._abort_reason = None, "", None
        self.probing, self.map_result = None, None
        self._abort_state = State.ABORTED
        mj = self.setup.map_job if job == "map" else None
        self.store.new_run(self.run_id, self.setup.name, trigger,
                           plan=f"map job {mj.name}" if mj else self.setup.plan.name,
                           artefact=", ".join(p.artefact.name for p in mj.placements) if mj
                           else self.setup.artefact.name, dialect=self.setup.dialect,
                           started_by=started_by)
        self._enter(State.PREPARE, "")
        self._task = asyncio.get_running_loop().create_task(self._run(self.run_id),
                                                            name=f"run-{self.run_id}")
        self._task.add_done_callback(lambda _t: lease.release())
        return self.run_id

    async def abort(self, source: str) -> bool:
        """Abort the current run (a person: HMI, CAN panel, a signal to ``rumba verify``):
        ABORTED; False when nothing runs. Returns once the run has ended, cleanup included."""
        return await self._cancel(State.ABORTED, f"aborted by {source}")

    async def interrupt(self, cause: str) -> bool:
        """Stop the current run because the daemon stops (``cause``): INTERRUPTED, as a crash
        would leave it (``rerun_interrupted`` runs it again at the next start)."""
        return await self._cancel(State.INTERRUPTED, f"interrupted by {cause}")

    async def shutdown(self, cause: str, report_wait_s: float | None = None) -> None:
        """The daemon stops (``cause``): the run INTERRUPTED, then the last run's report let
        finish for ``report_wait_s`` (default ``REPORT_STOP_WAIT_S``) and else cancelled,
        journaled failed with the reason (``report_job.settle``): nothing is left running or
        'writing' when the journal closes."""
        self.closing = True  # while it stops: a follow-up starts no verification run
        try:
            await self.interrupt(cause)
            # a follow-up being written (the unattended compensation: bounded by its budget)
            # ends its transaction while the report finishes
            follow = self._follow_task if self.following is not None else None
            await asyncio.gather(
                asyncio.wait({follow}) if follow is not None and not follow.done() else
                asyncio.sleep(0),
                report_job.settle(self._report_task, REPORT_STOP_WAIT_S if report_wait_s is None
                                  else report_wait_s))
        finally:
            self.closing = False

    async def _cancel(self, state: State, reason: str) -> bool:
        if not self.busy or self._task is None:
            return False
        if self._abort_reason is None:  # the first stop names the cause; repeats change nothing
            self._abort_reason, self._abort_state = reason, state
        self._task.cancel()
        await await_run(self._task)
        return True

    async def wait(self) -> dict[str, Any]:
        """Wait for the current run to end and its report to be written (or fail); returns
        the final status (``rumba verify`` prints the report's path from it)."""
        if self._task is not None:
            await await_run(self._task)
        if self._report_task is not None:
            await await_run(self._report_task)
        return self.status()

    # ---------------------------------------------------------------------------------- run
    async def _run(self, run_id: str) -> None:
        """The steps in order, each handed the previous one's result."""
        try:
            if not self.link_ok:
                await self.reconnect()
            if self._controller_dirty:  # the last stop could not reach the controller
                await self._clear_leftover()
            if self.job == "map":  # placements, operator prompts, the map fit
                await self._map_steps(run_id)
                return
            reference = self.store.last_good(self.setup.name, before=run_id)  # targets
            drift_ref = self._drift_reference(run_id)  # a person's baseline
            prepared = await self._prepare_program(run_id, reference)
            self.step = START_READS  # a stop here cuts no program: none was loaded yet
            await self.temps.start(run_id, self.clock.t_s())  # before the program: 0
            self.step = None  # STREAM proper: the program is loaded and sent next
            hits = await self._capture(prepared)
            hits = await self._reprobe(run_id, hits, reference)
            self.step = END_READS  # a stop from here to IDENTIFY cuts no touch: said so
            await self.temps.end(run_id, self.clock.t_s())
            self._raise_if_stopped()
            analysis = await self._identify(run_id, hits, drift_ref)
            self._raise_if_stopped()
            judgement = self._judge(run_id, analysis, drift_ref)
            self._raise_if_stopped()
            self._enter(State.WRITE_BACK)
            await self._write_back(Verdict(judgement.status, run_id, judgement.summary,
                                           judgement.reasons), strict=True)
            self._raise_if_stopped()
            self.store.mark_written_back(run_id)
            # the report is rendered after the run's end is published, in a worker
            self._report_task = report_job.start(self, run_id, analysis, judgement)
            self._enter(State.IDLE, "")
        except asyncio.CancelledError:
            # An abort (HMI, CAN, CLI signal) or the service stopping: the phase is the state
            # the run was in. The cleanup runs to its end whatever cancels us meanwhile.
            unasked = self._abort_reason is None  # the event loop ending: the daemon stops
            if unasked:
                self._abort_reason = "interrupted by the daemon stopping"
                self._abort_state = State.INTERRUPTED
            await self._end(run_id, self._abort_state, f"{self._abort_reason} {self.during()}",
                            stop=True)
            if unasked:
                raise
        except ControllerAborted as e:  # reset / abort pressed on the CNC itself
            await self._end(run_id, State.ABORTED, f"aborted on the controller "
                            f"{self.during()}: {e}", stop=True)
        except (ControllerSilent, LinkError) as e:
            # rumba lost the run (a link down, no results any more): INTERRUPTED, unless the
            # link delivered data that fails validation (a malformed result: FAILED)
            state = State.FAILED if isinstance(e, MalformedResult) else State.INTERRUPTED
            if isinstance(e, LinkError):
                self.link_ok = False
            await self._end(run_id, state, f"{str(e) or type(e).__name__} "
                            f"({self.during()})", stop=True)
        except (RunFailed, ControllerAlarm, pipeline.PipelineError) as e:
            # Whatever failed, the controller may still run the program (a timeout, a lost
            # result): stop it, or the next LoadProgram is refused.
            await self._end(run_id, State.FAILED, f"{str(e) or type(e).__name__} "
                            f"({self.during()})", stop=True)
        except Exception as e:  # a bug must not kill the daemon: the run fails with the cause
            log.exception("run %s crashed", run_id)
            await self._end(run_id, State.FAILED, f"internal error {self.during()}: "
                            f"{type(e).__name__}: {e}", stop=True)
        else:  # outside the run's handlers: a cancel here ends no DONE run as ABORTED
            await self._follow_up(run_id)

    async def _follow_up(self, run_id: str) -> None:
        """The run's follow-up (``after_run``: the unattended compensation, awaited when it is
        a coroutine), still in the run's task and under its machine lock; meanwhile a start is
        refused (``following``) and a stop waits for it (``shutdown``)."""
        if self.after_run is None:
            return
        self._follow_task = asyncio.current_task()
        self.following = f"run {run_id}'s follow-up (unattended compensation) is under way"
        try:
            out = self.after_run(self, run_id)
            if inspect.isawaitable(out):
                await out
        except asyncio.CancelledError:
            raise
        except Exception:  # the run is done and reported; a follow-up must not undo it
            log.exception("after run %s", run_id)
        finally:
            self.following = None

    async def _prepare_program(self, run_id: str, reference: tuple[str, Analysis] | None
                               ) -> pipeline.Prepared:
        """PREPARE: the checked program and its touch table (targets from the last good run)."""
        prepared = await asyncio.to_thread(self._prepare, self.setup, run_id,
                                           reference[1] if reference else None)
        self._raise_if_stopped()
        self.total, self.estimated_s = prepared.job.touch_count, prepared.estimated_s
        self.store.set_state(run_id, "PREPARE", touch_total=self.total)
        self._enter(State.STREAM)
        return prepared

    async def _identify(self, run_id: str, hits: list[ProbeHit],
                        reference: tuple[str, Analysis] | None) -> pipeline.RunAnalysis:
        """IDENTIFY: hits → centres → estimate → analyses, recorded with the reference run."""
        self._enter(State.IDENTIFY)
        analysis = await asyncio.to_thread(self._analyse, self.setup, hits, run_id, reference)
        analysis = self.temps.with_summary(run_id, analysis)  # the run's temperatures
        self.store.save_centres(run_id, analysis.centre_rows)
        self.store.save_analysis(run_id, analysis.data)
        return analysis

    def _drift_reference(self, run_id: str) -> tuple[str, Analysis] | None:
        """The machine's baseline (``store.baselines``: a run a person accepted) and its
        analysis, the reference drift is judged against; None: "drift not checked"."""
        base = baselines.reference(self.store, self.setup.name, before=run_id)
        self.baseline = base[0] if base else None
        return (base[0].run_id, base[1]) if base else None

    def _judge(self, run_id: str, analysis: pipeline.RunAnalysis,
               reference: tuple[str, Analysis] | None) -> Judgement:
        """JUDGE: the verdict against the tolerances and the drift from the reference run."""
        self._enter(State.JUDGE)
        j = judge(analysis.data, self.setup.tolerances, reference[1] if reference else None)
        self.store.save_judgement(run_id, j)
        self.verdict = {"status": j.status, "summary": j.summary, "reasons": list(j.reasons),
                        "at": time.time(),  # when judged: the HMI shows its date and age
                        # the figures with their definitions, the drift baseline
                        "figures": figures_json(run_figures(analysis.data)),
                        "baseline": self.baseline.as_dict() if self.baseline else None,
                        # each temperature channel's start → end (the HMI card)
                        "temperatures": temperature_lines(analysis.data),
                        # the rotary axes' indexing repeatability behind the link u
                        "index_scatter": index_scatter_lines(analysis.data)}
        return j


