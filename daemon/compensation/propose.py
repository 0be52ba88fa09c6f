"""Compensation write-back, the planning half: a run's estimate against the controller model
it ran on (stored at run end, ``daemon.compensation.identified``), the plan of changes, guards
and refusals, and that controller model (machine file + the compensations the journal says were
written)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from contracts.controller_kinematics import ControllerKinematics, controller_kinematics
from contracts.messages import ProbeHit
from daemon.analysis.figures import LINK_DEFINITION, Figure, plan_figures, run_figures
from daemon.compensation import identified
from daemon.compensation import journal as cj
from daemon.compensation.identified import CompensationRefused, run_centres
from daemon.machines.setup import MachineSetup
from daemon.store.journal import Store, StoreError
from identification.compensation import (
    CompensationPlan,
    GuardResult,
    Guards,
    ParamChange,
    apply_changes,
    check_guards,
)
from identification.estimate import Estimate
from identification.kinematics import Machine
from identification.model import Centres

if TYPE_CHECKING:  # the analysis pipeline (scipy …) only where a run is analysed
    from daemon.analysis.pipeline import RunAnalysis
    from daemon.analysis.result import Analysis

__all__ = ["CompensationRefused", "run_centres"]  # re-exported: their home is ``identified``
log = logging.getLogger("rumba.compensate")


class ControllerModelError(Exception):
    """The controller's kinematics disagree with the journal (changed outside rumba)."""


def spec_of(setup: MachineSetup) -> ControllerKinematics | None:
    """The machine file's ``controller_kinematics`` section, checked against the machine; None
    when the machine file has none."""
    section = getattr(setup.machine_file, "controller_kinematics", None)
    if section is None:
        return None
    return controller_kinematics(section, setup.machine, f"machine {setup.name}")


# the controller family whose addresses each dialect's machine holds (daemon.yaml dialect)
FAMILY_OF_DIALECT = {"fanuc": "fanuc", "haas": "haas", "siemens": "siemens",
                     "heidenhain": "heidenhain", "linuxcnc": "linuxcnc"}


def check_family(setup: MachineSetup, spec: ControllerKinematics) -> None:
    """The machine file's controller addresses are of the configured controller (issue 23:
    $TC_CARR values proposed for a machine configured as Fanuc), else ``CompensationRefused``
    naming both."""
    want = FAMILY_OF_DIALECT.get(str(setup.dialect), str(setup.dialect))
    if spec.family != want:
        example = spec.params[0].address if spec.params else ""
        raise CompensationRefused(
            f"machine {setup.name} is configured as {setup.dialect} (daemon.yaml dialect) but "
            f"its machine file's controller_kinematics holds {spec.family} addresses "
            f"({example}, …): give the {want} control's own parameters in the machine file "
            "(or the right dialect); nothing is proposed")


def guards_of(spec: ControllerKinematics) -> Guards:
    return Guards(spec.max_change_um * 1e-3, spec.max_change_urad * 1e-6,
                  spec.max_total_um * 1e-3)


def unit_of(kind: str) -> tuple[str, float]:
    """The section's unit of a value and its factor from the model's (mm, rad)."""
    return ("mm", 1.0) if kind == "pivot" else ("urad", 1e6)


def is_local_linuxcnc(setup: MachineSetup, spec: ControllerKinematics | None) -> bool:
    """LinuxCNC on this PC: the link's ``mode: local``, or linuxcncrsh on a loopback host."""
    from daemon.hosts import is_loopback

    link = setup.link
    if spec is None or spec.family != "linuxcnc" or getattr(link, "transport", "") != "linuxcnc":
        return False
    return link.mode == "local" or is_loopback(link.host)


# ------------------------------------------------------------------------- controller model


def cumulative_deltas(store: Store, machine: str, before: float | None = None
                      ) -> dict[str, float]:
    """Per parameter: the sum of the deltas (mm / rad) written to the controller so far."""
    out: dict[str, float] = {}
    for row in cj.written(store, machine, before):
        for v in row.values:
            out[v.name] = out.get(v.name, 0.0) + v.delta
    return out


def controller_model(setup: MachineSetup, store: Store, *, before: float | None = None,
                     check_hal: bool = True) -> Machine:
    """The model the controller runs: the machine file's, changed by every compensation
    written before ``before`` (default: all). For a LinuxCNC on this PC the live kinematics
    pins must equal the journal's values, else ``ControllerModelError``."""
    spec = spec_of(setup)
    if spec is None:
        return setup.machine
    params = spec.to_math()
    deltas = cumulative_deltas(store, setup.name, before)
    if check_hal and before is None and is_local_linuxcnc(setup, spec):
        check_hal_agrees(setup, spec, store)
    changes = [ParamChange(p.name, p.kind, deltas[p.name], 0.0, True, "journal")
               for p in params if abs(deltas.get(p.name, 0.0)) > 0.0]
    return apply_changes(setup.machine, params, changes) if changes else setup.machine


def changed_since(store: Store, machine: str, started_at: float) -> cj.CompensationRow | None:
    """The compensation written after ``started_at`` that left the controller's model other
    than it was when the run started (applied, not undone by a rollback since), or None."""
    before, now = cumulative_deltas(store, machine, started_at), cumulative_deltas(store, machine)
    if all(abs(before.get(k, 0.0) - now.get(k, 0.0)) < 1e-12 for k in {*before, *now}):
        return None
    written = cj.written(store, machine)
    later = [r for r in written if (r.applied_at or 0.0) >= started_at] or written
    return later[-1] if later else None


def expected_values(spec: ControllerKinematics, store: Store, machine: str
                    ) -> dict[str, tuple[str, float]]:
    """name → (address, value the controller should hold): the journal's last written value,
    else the machine file's."""
    current = cj.current_values(store, machine)
    return {p.name: (p.address, current[p.name].new if p.name in current else float(p.value))
            for p in spec.params}


def check_hal_agrees(setup: MachineSetup, spec: ControllerKinematics, store: Store) -> None:
    from drivers.linuxcnc import halkins

    # the section's (and journal's) orientation values are µrad of the held link; the kins
    # pin holds it in deg (xyzbc_head_kins, programs/compensation/linuxcnc.py)
    want = {n: (a, v if spec.param(n).kind == "pivot" else float(np.degrees(v * 1e-6)))
            for n, (a, v) in expected_values(spec, store, setup.name).items()}
    try:
        got = halkins.read_pins([a for a, _ in want.values()])
    except halkins.HalError as e:
        if spec.read_back == "when_written" and not cj.written(store, setup.name):
            # rumba never wrote to this controller: its model is the machine file's, as before
            # compensation existed; the pins cannot be read (no HAL access for this user).
            # ``read_back: required`` makes readable pins a condition of every run and write.
            return
        raise ControllerModelError(f"machine {setup.name}: cannot read the kinematics pins: "
                                   f"{e}") from None
    bad = [f"{a} = {got[a]:g} (journal/machine file: {v:g})" for a, v in want.values()
           if not halkins.agrees(got[a], v)]
    if bad:
        raise ControllerModelError(
            f"machine {setup.name}: LinuxCNC's kinematics differ from rumba's journal: "
            f"{'; '.join(bad)} — someone changed the kinematics outside rumba; restore them "
            "or record the change before identifying against this controller")


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
    # issue 23: the run's own figures (the report's), and where the link values come from
    run_figures: tuple[Figure, ...] = ()
    links_from: str = "run"  # "run": the report's estimate | "refit": stored centres again

    def figures(self) -> tuple[Figure, ...]:
        """The run's figures, then the plan's link-caused and predicted-after distortions."""
        return (*self.run_figures, *plan_figures(self.plan.distortion_before_um,
                                                 self.plan.distortion_after_um))

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
    analysis = store.analysis(run_id)
    links = est.links_si()
    same = analysis is not None and set(analysis.links) == set(links) and all(
        abs(analysis.links[n].value - v) <= 1e-3 for n, (v, _, _) in links.items())
    return Proposal(run_id, spec, plan, guard, values,
                    links, k, refusals, {ch.name: why for ch, why in guard.skipped},
                    {n: v for n, (_, v) in expected_values(spec, store, setup.name).items()},
                    run_figures(analysis) if analysis is not None else (),
                    "run" if same else "refit")


# ------------------------------------------------------------------------ cumulative guard


def _held(setup: MachineSetup, store: Store, spec: ControllerKinematics,
          row: cj.CompensationRow) -> bool:
    """Did ``row``'s verification run confirm it? Its own plan (against the model it ran
    on) would move none of the values ``row`` wrote by more than their expanded uncertainty.
    A compensation that did not hold is no baseline: a second change on top of it is exactly
    the walk the cumulative guard stops."""
    if not row.verify_run_id:
        return False
    try:
        v = store.run(row.verify_run_id)
        model = controller_model(setup, store, before=v.started_at, check_hal=False)
        _, plan = identified.stored_or_computed(setup, store, v.id, model, spec.to_math(),
                                                setup.tolerances.coverage_k)
    except (CompensationRefused, StoreError, ValueError):
        return False
    names = {x.name for x in row.values}
    return all(abs(ch.delta) <= ch.u_expanded or not ch.observable
               for ch in plan.changes if ch.name in names)


def baseline(setup: MachineSetup, store: Store, spec: ControllerKinematics, run_id: str
             ) -> tuple[dict[str, float], str]:
    """The last verified baseline: per parameter the deltas (mm / rad) written up to the last
    compensation (still applied) that its verification run confirmed, else none (the machine
    file's values); and what it is, for messages. ``run_id``'s own compensation verification
    is never a baseline for itself (it wants to change the values: they did not hold)."""
    rows = cj.written(store, setup.name)
    for i in range(len(rows) - 1, max(-1, len(rows) - 6), -1):  # the 5 newest at most
        r = rows[i]
        if r.state == "applied" and r.verify_run_id != run_id and _held(setup, store, spec, r):
            out: dict[str, float] = {}
            for w in rows[:i + 1]:
                for v in w.values:
                    out[v.name] = out.get(v.name, 0.0) + v.delta
            return out, f"compensation #{r.id} verified by run {r.verify_run_id}"
    return {}, "the machine file's values"


def cumulative_refusals(setup: MachineSetup, store: Store, spec: ControllerKinematics,
                        values: list[cj.ValueChange], run_id: str) -> list[str]:
    """Each value's changes since the last verified baseline, this one included, within
    ``guards.max_cumulative_um`` / ``_urad`` (default: the per-change limit); the refusals,
    with the numbers."""
    base, what = baseline(setup, store, spec, run_id)
    now = cumulative_deltas(store, setup.name)
    out = []
    for v in values:
        kind = spec.param(v.name).kind
        limit = (spec.max_cumulative_um or spec.max_change_um) * 1e-3 if kind == "pivot" \
            else (spec.max_cumulative_urad or spec.max_change_urad) * 1e-6
        earlier = now.get(v.name, 0.0) - base.get(v.name, 0.0)
        total = earlier + v.delta
        if abs(total) > limit * (1 + 1e-9):
            f, unit, key = (1e3, "µm", "um") if kind == "pivot" else (1e6, "µrad", "urad")
            out.append(f"{v.name}: {total * f:+.1f} {unit} since the last verified baseline "
                       f"({what}: earlier {earlier * f:+.1f} {unit}, this change "
                       f"{v.delta * f:+.1f} {unit}) is over the cumulative limit "
                       f"{limit * f:.1f} {unit} (guards.max_cumulative_{key}); "
                       "verify that the last compensation held first")
    return out


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
