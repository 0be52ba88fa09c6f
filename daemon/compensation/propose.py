"""Compensation write-back, the planning half: a run's estimate against the controller model
it ran on (stored at run end, ``daemon.compensation.identified``; the model: ``model``), the
plan of changes, the worth rule, guards and refusals, and the program a confirmation would
write with its listing (``listing``)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from contracts.controller_kinematics import ControllerKinematics
from contracts.messages import ProbeHit
from daemon.analysis.figures import LINK_DEFINITION, Figure, plan_figures, run_figures
from daemon.compensation import identified
from daemon.compensation import journal as cj
from daemon.compensation.cumulative import cumulative_refusals
from daemon.compensation.identified import CompensationRefused, run_centres
from daemon.compensation.listing import current_spec, expected_values, program_of
from daemon.compensation.model import (
    ControllerModelError,
    changed_since,
    check_family,
    check_hal_agrees,
    controller_model,
    cumulative_deltas,
    guards_of,
    is_local_linuxcnc,
    spec_of,
    unit_of,
)
from daemon.machines.setup import MachineSetup
from daemon.store.journal import RunRow, Store
from identification.compensation import (
    CompensationPlan,
    GuardResult,
    ParamChange,
    check_guards,
)
from identification.estimate import Estimate
from identification.kinematics import Machine
from identification.model import Centres
from programs.compensation import CompensationOutput

if TYPE_CHECKING:  # the analysis pipeline (scipy …) only where a run is analysed
    from daemon.analysis.pipeline import RunAnalysis
    from daemon.analysis.result import Analysis

# re-exported: their home is ``identified`` and ``model``
__all__ = ["CompensationRefused", "ControllerModelError", "changed_since", "check_family",
           "check_hal_agrees", "controller_model", "cumulative_deltas", "guards_of",
           "is_local_linuxcnc", "run_centres", "spec_of", "unit_of"]
log = logging.getLogger("rumba.compensate")


# ----------------------------------------------------------------------------- planning


@dataclass
class Proposal:
    """What ``rumba compensate RUN`` shows and (with --confirm) applies."""

    run_id: str
    spec: ControllerKinematics
    plan: CompensationPlan
    guard: GuardResult
    values: list[cj.ValueChange]  # accepted changes, controller units
    links: dict[str, tuple[float, float, str]]  # re-identified against the controller model
    coverage_k: float
    refusals: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)  # name → why not applied
    current: dict[str, float] = field(default_factory=dict)  # name → value the control holds
    # the run's own figures (the report's), and where the link values come from
    run_figures: tuple[Figure, ...] = ()
    links_from: str = "run"  # "run": the report's estimate | "refit": stored centres again
    # what a confirmation would write from the values the controller holds now: the program
    # and its listing (every address, the value as written); None when nothing is accepted
    program: CompensationOutput | None = None
    # why nothing is proposed although the data would allow changes (the worth rule,
    # identification.worth: too small a gain, or a PASS verification run); "" otherwise
    not_worth: str = ""

    def figures(self) -> tuple[Figure, ...]:
        """The run's figures, then the link-caused distortion and the one predicted once the
        accepted changes (these, not every observable one) are written."""
        after = self.guard.after_um or self.plan.distortion_after_um
        return (*self.run_figures, *plan_figures(self.plan.distortion_before_um, after))

    def links_text(self) -> str:
        """Where the link values come from, one sentence."""
        if self.links_from == "run":
            return LINK_DEFINITION + " — the same as the run's report"
        return ("link errors re-identified from the run's stored centres (first visit per "
                "pose, no drift model) against the controller model: the run's report was made "
                "before the machine or artefact file changed and may differ")


def reidentify(setup: MachineSetup, store: Store, run_id: str, machine: Machine
               ) -> tuple[Estimate, Centres]:
    """The run's stored centres (validation poses held out, as the run did) → estimate,
    identified now (what the stored estimate must equal; tests and benchmarks)."""
    c = identified.estimation_centres(setup, run_centres(setup, store, run_id))
    return identified.identify(setup, c, run_id, machine), c


def quality_refusals(store: Store, run_id: str, est: Estimate, compensated: list[str]
                     ) -> list[str]:
    """Why the run must not be compensated from: ERROR verdict, unstable (ill-conditioned)
    or unconverged estimate, an observability warning naming a compensated link."""
    out = []
    v = store.verdict(run_id)
    if v is None:
        out.append(f"run {run_id} has no verdict")
    elif v["status"] == "ERROR":
        out.append(f"run {run_id} verdict is ERROR ({'; '.join(v['reasons'])[:160]})")
    if not est.converged:
        out.append(f"estimate {est.status}")
    if not np.isfinite(est.residual_rms_um) or not np.all(np.isfinite(est.std)):
        out.append("estimate not finite")
    unstable = [w for w in est.warnings if "condition" in w.lower()]
    if unstable:
        out.append(f"estimate unstable: {unstable[0]}")
    # est.unobservable lists the structural directions (absorbed by the setup, always there);
    # a warning of the estimate naming a compensated link means its value is not to be trusted
    for w in est.warnings:
        hit = [n for n in compensated if n in w]
        if hit and "observ" in w.lower():
            out.append(f"compensated {', '.join(hit)}: {w}")
    return out


def to_value_changes(spec: ControllerKinematics, store: Store, machine: str,
                     changes: list[ParamChange]) -> list[cj.ValueChange]:
    """Math changes → controller values (old = what the controller holds now)."""
    current = expected_values(spec, store, machine)
    out = []
    for ch in changes:
        p = spec.param(ch.name)
        unit, factor = unit_of(p.kind)
        old = current[ch.name][1]
        new = round(old + ch.delta * factor, 6)  # nm / µrad·1e-6: what halcmd reads back
        out.append(cj.ValueChange(ch.name, p.address, unit, old, new, (new - old) / factor,
                                  float(ch.u_expanded)))
    return out


def propose(setup: MachineSetup, store: Store, run_id: str) -> Proposal:
    """Re-identify ``run_id`` against the controller model at the run's start, plan the
    changes, check the guards and the run's quality (refusals listed, not raised)."""
    spec = spec_of(setup)
    if spec is None:
        raise CompensationRefused(f"machine {setup.name}: its machine file has no "
                                  "controller_kinematics section (nothing rumba may write)")
    check_family(setup, spec)
    run = store.run(run_id)
    if run.machine != setup.name:
        raise CompensationRefused(f"run {run_id} is of machine {run.machine}, not "
                                  f"{setup.name}")
    model = controller_model(setup, store, before=run.started_at, check_hal=False)
    k = setup.tolerances.coverage_k
    est, plan = identified.stored_or_computed(setup, store, run_id, model, spec.to_math(), k)
    guard = check_guards(plan, guards_of(spec))
    done = passed_verification(store, setup.name, run, plan) if guard.accepted else ""
    if done:  # rule 5 of the worth rule
        guard = GuardResult([], [*guard.skipped, *((ch, done) for ch in guard.accepted)], [],
                            [], plan.distortion_before_um, done)
    compensated = [n for n, v in plan.links_compensable.items() if abs(v) > 1e-12]
    refusals = quality_refusals(store, run_id, est, compensated) + list(guard.refused)
    later = changed_since(store, setup.name, run.started_at)
    if later is not None:  # the deltas would be added to values they were not computed for
        refusals.append(f"the controller's model changed after run {run_id} started (journal "
                        f"#{later.id}, {later.state}): verify again and compensate from that "
                        "run")
    values = to_value_changes(spec, store, setup.name, list(guard.accepted))
    if values and later is None:
        refusals += cumulative_refusals(setup, store, spec, values, run_id)
    program = None
    if values:
        try:
            program = program_of(current_spec(spec, store, setup.name), values, run_id,
                                 setup.name)
        except CompensationRefused as e:
            refusals.append(str(e))
    analysis = store.analysis(run_id)
    links = est.links_si()
    same = analysis is not None and set(analysis.links) == set(links) and all(
        abs(analysis.links[n].value - v) <= 1e-3 for n, (v, _, _) in links.items())
    return Proposal(run_id, spec, plan, guard, values,
                    links, k, refusals, {ch.name: why for ch, why in guard.skipped},
                    {n: v for n, (_, v) in expected_values(spec, store, setup.name).items()},
                    run_figures(analysis) if analysis is not None else (),
                    "run" if same else "refit", None if refusals else program, guard.not_worth)


def passed_verification(store: Store, machine: str, run: RunRow, plan: CompensationPlan
                        ) -> str:
    """Rule 5 of the worth rule (``identification.worth``): why nothing is proposed from
    ``run`` — it is the run that verifies the machine's last applied compensation (the first
    finished run after it) and it PASSed; "" otherwise. Says whether the written values held
    (this run's plan moves none of them beyond its U) or not (then the cumulative guard's
    walk is what a further change would start: a person investigates first)."""
    last = cj.last_applied(store, machine)
    if last is None or last.applied_at is None or run.started_at < last.applied_at \
            or run.verdict != "PASS":
        return ""
    verifier = last.verify_run_id or min(
        (r for r in store.runs(machine, 200) if r.started_at >= last.applied_at
         and r.state in ("DONE", "IMPORTED")), key=lambda r: r.started_at, default=run).id
    if verifier != run.id:
        return ""
    written = {v.name for v in last.values}
    moved = [ch.name for ch in plan.changes if ch.name in written and ch.observable
             and abs(ch.delta) > ch.u_expanded]
    held = ("its values held" if not moved else
            f"{', '.join(moved)} would move again beyond U (the compensation did not hold as "
            "predicted: investigate before changing it again)")
    return (f"run {run.id} verifies compensation #{last.id} (from run {last.run_id}) and "
            f"PASSed; {held}: a machine within its limits is not changed again from its "
            "verification run")


def journal_analyse(journal: Path) -> Callable[..., RunAnalysis]:
    """``pipeline.analyse`` identifying against the controller model of the journal at
    ``journal`` (its own connection: it runs in the session's worker thread); for
    ``Session(analyse=…)``. A controller changed outside rumba fails the run. For a machine
    rumba may compensate, the run's estimate for its compensation view is identified and
    stored here too, once, off the event loop (``identified.at_run_end``)."""

    def analyse(setup: MachineSetup, hits: Sequence[ProbeHit], run_id: str = "run",
                reference: tuple[str, Analysis] | None = None) -> RunAnalysis:
        from daemon.analysis import pipeline

        store = Store(journal)
        try:
            try:
                machine = controller_model(setup, store)
            except ControllerModelError as e:
                raise pipeline.PipelineError(str(e)) from None
            out = pipeline.analyse(setup, hits, run_id, reference, controller=machine)
            _store_estimate(setup, store, run_id, out)
            return out
        finally:
            store.close()

    return analyse


def _store_estimate(setup: MachineSetup, store: Store, run_id: str, out: RunAnalysis) -> None:
    """The compensation view's estimate of a run just analysed (machines with a
    ``controller_kinematics`` section); a failure here costs the view a later computation,
    never the run."""
    try:
        spec = spec_of(setup)
        if spec is None:
            return
        model = controller_model(setup, store, before=store.run(run_id).started_at,
                                 check_hal=False)
        identified.at_run_end(setup, store, run_id, out.centre_rows, model, spec.to_math(),
                              setup.tolerances.coverage_k, out.estimate)
    except Exception as e:  # any failure (a plan's SVD included) must not fail the run
        log.warning("%s %s: compensation estimate not stored (computed when asked): %s",
                    setup.name, run_id, e)
