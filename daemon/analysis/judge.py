"""The verdict: link errors and volumetric distortion against tolerances and a baseline run."""
# Absolute and relative to the machine's baseline (a run a person accepted) →
# PASS / WARN / FAIL with one reason per violated limit.
# Decision rule (ISO 14253-1, stated in every reason and in the report, ``decision_rule``): a
# value whose magnitude exceeds a ``fail`` limit fails; one that exceeds ``warn`` — or whose
# magnitude plus ``k`` standard uncertainties reaches ``fail`` (conformance not proven) —
# warns. Units follow the ``Analysis``: µm for translations and distortions, µrad for rotations.

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from daemon.analysis.figures import LABELS, VOLUMETRIC, run_figures, volumetric_max_um
from daemon.analysis.result import Analysis
from daemon.analysis.verdict_text import duration_text
from daemon.machines.tolerances import Limit, Tolerances
from identification.outliers import REPROBE_REPEAT_BASE
from identification.uncertainty import expanded_k

STATUS_ORDER = {"PASS": 0, "WARN": 1, "FAIL": 2, "ERROR": 3}
"""ERROR: the measurement itself is not trusted (health limits), so no statement on the machine."""


@dataclass(frozen=True)
class Check:
    quantity: str
    value: float
    std: float | None
    unit: str
    status: str
    limit: str  # human-readable limit that decided
    reference: float | None = None  # the baseline's value (drift checks)
    reference_run: str | None = None  # the baseline run (drift checks)

    def as_dict(self) -> dict[str, Any]:
        return self.__dict__.copy()


@dataclass(frozen=True)
class Judgement:
    status: str  # PASS | WARN | FAIL | ERROR (measurement not trusted)
    reasons: tuple[str, ...]
    checks: tuple[Check, ...]
    summary: str


def _grade(quantity: str, value: float, std: float | None, unit: str, lim: Limit,
           k: float, reference: float | None, reference_run: str | None = None) -> list[Check]:
    out = []
    mag = abs(value)
    u = std or 0.0
    status, why = "PASS", _fmt_limit(lim.warn, lim.fail, unit)
    if lim.fail is not None and mag > lim.fail:
        status, why = "FAIL", f"|value| > fail {lim.fail:g} {unit}"
    elif lim.warn is not None and mag > lim.warn:
        status, why = "WARN", f"|value| > warn {lim.warn:g} {unit}"
    elif lim.fail is not None and u > 0 and mag + k * u > lim.fail:
        status, why = "WARN", (f"|value| + {k:.3g}u ≥ fail {lim.fail:g} {unit} "
                               "(conformance not proven)")
    if lim.warn is not None or lim.fail is not None:
        out.append(Check(quantity, value, std, unit, status, why))
    if reference is not None and (lim.drift_warn is not None or lim.drift_fail is not None):
        d = value - reference
        status, why = "PASS", _fmt_limit(lim.drift_warn, lim.drift_fail, unit, "drift ")
        if lim.drift_fail is not None and abs(d) > lim.drift_fail:
            status, why = "FAIL", f"drift > {lim.drift_fail:g} {unit}"
        elif lim.drift_warn is not None and abs(d) > lim.drift_warn:
            status, why = "WARN", f"drift > {lim.drift_warn:g} {unit}"
        out.append(Check(f"{quantity} drift", d, std, unit, status, why, reference,
                         reference_run))
    return out


def _fmt_limit(warn: float | None, fail: float | None, unit: str, prefix: str = "") -> str:
    parts = [f"{prefix}warn {warn:g}" if warn is not None else "",
             f"{prefix}fail {fail:g}" if fail is not None else ""]
    return " / ".join(p for p in parts if p) + f" {unit}"


def _reason(c: Check) -> str:
    if math.isnan(c.value):  # nothing measured (a channel not read): the limit says why
        return f"{c.quantity}: {c.limit}"
    std = f" ± {c.std:.2f}" if c.std else ""
    if c.reference is not None:
        return (f"{c.quantity}: {c.value:+.2f}{std} {c.unit} since baseline run "
                f"{c.reference_run or '?'} (was {c.reference:+.2f}); {c.limit}")
    return f"{c.quantity} = {c.value:+.2f}{std} {c.unit}: {c.limit}"


NO_BASELINE = "drift not checked: no baseline"


def judge(analysis: Analysis, tol: Tolerances, last_good: Analysis | None = None) -> Judgement:
    """Grade one run's analysis against ``tol``.

    ``last_good`` is the analysis of the machine's baseline run (a run a person
    accepted, ``daemon.store.baselines``): drift is judged against it; without one, and with
    drift limits set, the reasons say "drift not checked: no baseline"."""
    checks: list[Check] = []
    ref_links = last_good.links if last_good is not None else {}
    ref_run = last_good.run_id if last_good is not None else None
    # The guard band k·u at coverage_k's normal coverage (k = 2: 95.45 %) for the stated u,
    # the standard deviation of a t on σ's residual dof (identification/uncertainty.py, one
    # definition with the compensation's U): 2.02 at ν = 24, 3.67 for k = 3 at ν = 8.3.
    dof = analysis.estimation.sigma_dof if analysis.estimation is not None else None
    k = tol.coverage_k
    if dof:
        k = expanded_k(float(dof), k)
    for name, est in sorted(analysis.links.items()):
        lim = tol.links.get(name) or (
            tol.default_rotation_urad if est.unit == "urad" else tol.default_translation_um)
        if lim is None:
            continue
        ref = ref_links[name].value if name in ref_links else None
        checks += _grade(name, float(est.value), est.std, _unit(est.unit), lim, k, ref, ref_run)
    if tol.volumetric_max_um is not None:
        vmax = volumetric_max_um(analysis)
        if vmax is None:
            checks.append(Check(LABELS[VOLUMETRIC], float("nan"), None, "µm", "FAIL",
                                "no volumetric distortion in the analysis"))
        else:
            ref = volumetric_max_um(last_good) if last_good else None
            checks += _grade(LABELS[VOLUMETRIC], vmax, None, "µm",
                             tol.volumetric_max_um, k, ref, ref_run)
    checks += thermal_checks(analysis, tol)
    checks += temperature_checks(analysis, tol)
    checks += _health(analysis, tol)
    missing = sorted(set(tol.links) - set(analysis.links))
    status = max((c.status for c in checks), key=STATUS_ORDER.__getitem__, default="PASS")
    if status == "ERROR":  # health first: the other numbers come from a suspect measurement
        checks.sort(key=lambda c: c.status != "ERROR")
    reasons = [_reason(c) for c in checks if c.status != "PASS"]
    # a repaired fault does not change the verdict, but the operator is told (and where)
    reasons += [_reason(c) for c in checks
                if c.status == "PASS" and c.quantity.startswith("measurement outlier")]
    reasons += [f"{n}: tolerance given but not identified in this run" for n in missing]
    if last_good is None and _has_drift_limits(tol):  # said, never silently dropped
        reasons.append(f"{NO_BASELINE} (a person sets one: rumba baseline set, or the HMI)")
    n_bad = sum(c.status != "PASS" for c in checks)
    summary = f"{status}: {len(checks)} checks, {n_bad} outside limits"
    vol = run_figures(analysis)[0]
    if vol.value is not None:  # the figure every surface shows, with its name
        summary += f"; {vol.text()}"
    return Judgement(status, tuple(reasons), tuple(checks), summary)


def decision_rule(k: float = 2.0) -> str:
    """The decision rule as the report states it (ISO 14253-1: how u enters the verdict)."""
    return (f"ISO 14253-1 decision rule, guard band k·u with k = {k:g} (95 % coverage; u is "
            "the standard deviation of the Student t of an a-posteriori σ, GUM-S1 6.4.9.4, "
            "and k the t's quantile over it): conformance zone "
            "|value| + k·u < fail limit and |value| ≤ warn limit → PASS; undecided zone "
            "fail − k·u ≤ |value| ≤ fail (conformance not proven) or warn < |value| ≤ fail → "
            "WARN; non-conformance |value| > fail limit → FAIL (the measured value decides "
            "there, without a guard band: the user's risk is not extended). Drift: value − "
            "baseline value against the drift limits. Health limits (sphere radius and form, "
            "residual, revisit shift) make the measurement untrusted → ERROR.")


def _has_drift_limits(tol: Tolerances) -> bool:
    lims = [*tol.links.values(), tol.default_rotation_urad, tol.default_translation_um,
            tol.volumetric_max_um]
    return any(lim is not None and (lim.drift_warn is not None or lim.drift_fail is not None)
               for lim in lims)


def thermal_checks(analysis: Analysis, tol: Tolerances) -> list[Check]:
    """The fitted TCP drift over the run per axis against ``thermal_drift_um``:
    WARN "machine not thermally stable". The links were estimated with the drift, so the
    reason names the machine's thermal state, never a link."""
    th = analysis.thermal
    # without its own limit the run's health limit on a revisit shift stands in for it: the
    # drift it was configured to catch is now fitted (and left out of the revisit shifts)
    lim = tol.thermal_drift_um if tol.thermal_drift_um is not None else tol.run_drift_um
    if lim is None or th is None or th.status != "selected":
        return []
    span = f" over {duration_text(th.span_min * 60)}" if th.span_min else ""
    tau = ""
    if th.tau_min is not None:
        tau = (f", τ {th.tau_min:.0f} min" if th.tau_bounded is None
               else f", τ at its {th.tau_bounded} bound {th.tau_min:.0f} min")
    out = []
    for axis, d in th.over_run_um.items():
        if d.value is None:
            continue
        bad = abs(d.value) > lim
        out.append(Check(f"thermal drift {axis}{span}", float(d.value), d.std, "µm",
                         "WARN" if bad else "PASS",
                         (f"machine not thermally stable: |drift| > {lim:g} µm ({th.shape}"
                          f"{tau}); the link errors are estimated with the drift, let the "
                          "machine warm up before trusting a trend" if bad
                          else f"thermal limit {lim:g} µm ({th.shape}{tau})")))
    return out


def temperature_checks(analysis: Analysis, tol: Tolerances) -> list[Check]:
    """Each limited temperature channel: outside its range or changed more
    than ``change_c`` over the run → WARN "machine not in its thermal condition" with the
    numbers; a limited channel not read at all → WARN (the limit could not be checked). Never
    FAIL: a temperature says the check ran warm, not that the geometry is out."""
    temps = analysis.temperatures or {}
    out = []
    for name, (lo, hi, change) in sorted(tol.temperatures.items()):
        t = temps.get(name)
        if t is None or t.get("min_c") is None:
            why = "; ".join(t.get("errors", [])) if t else "no reading in this run"
            out.append(Check(f"temperature {name}", float("nan"), None, "°C", "WARN",
                             f"temperature limit not checked: channel not read ({why})"))
            continue
        if lo is not None or hi is not None:
            worst = t["min_c"] if lo is not None and t["min_c"] < lo else t["max_c"]
            bad = (lo is not None and t["min_c"] < lo) or (hi is not None and t["max_c"] > hi)
            rng = f"[{'' if lo is None else f'{lo:g}'}, {'' if hi is None else f'{hi:g}'}] °C"
            out.append(Check(f"temperature {name}", float(worst), None, "°C",
                             "WARN" if bad else "PASS",
                             f"machine outside its temperature range {rng} during the check"
                             if bad else f"range {rng}"))
        if change is not None:
            out.append(_change_check(name, t, change))
    return out


def _change_check(name: str, t: dict, limit: float) -> Check:
    """A channel's change over the run against ``limit``: measured between its first and last
    readings (contracts.temperatures.summarise); a change over less than start → end (a start or
    end not read) that stays inside the limit is WARN "not checked over the whole run", one
    reading alone WARN "not checked" — never a change of 0 claimed from one value."""
    what = f"temperature change {name} over the run"
    c = t.get("change_c")
    if c is None:
        return Check(what, float("nan"), None, "°C", "WARN",
                     f"temperature change limit {limit:g} °C not checked: one reading only "
                     f"({t.get('first_at') or 'start'})")
    over = t.get("change_over") or "start → end"
    first, last = t.get("first_c", t.get("start_c")), t.get("last_c", t.get("end_c"))
    span = "" if over == "start → end" else f", {over}"
    if abs(c) > limit:
        return Check(what, float(c), None, "°C", "WARN",
                     f"machine not thermally stable: |change| > {limit:g} °C "
                     f"({first:.1f} → {last:.1f} °C{span})")
    if span:
        return Check(what, float(c), None, "°C", "WARN",
                     f"temperature change limit {limit:g} °C not checked over the whole run: "
                     f"{c:+.1f} °C over {over} only")
    return Check(what, float(c), None, "°C", "PASS", f"change limit {limit:g} °C")


def _health(analysis: Analysis, tol: Tolerances) -> list[Check]:
    """Is the measurement trustworthy? A ball-pose whose sphere radius departs from the run's
    median (thesis §3.4: dirt, a chip, a damaged ball, an early trigger) or a large estimation
    residual makes every identified number suspect: ERROR, naming where."""
    out = _outliers(analysis)
    # visits the outlier test named are judged there (and a repaired one is not used)
    named = {(o.pose, o.ball, o.repeat) for o in analysis.outliers or ()}
    health = tuple(h for h in analysis.health if (h.pose, h.ball, h.repeat) not in named)
    devs = [h.radius_dev_um for h in health if h.radius_dev_um is not None]
    if tol.sphere_radius_spread_um is not None and devs:
        med = sorted(devs)[len(devs) // 2]
        worst = max(health, key=lambda h: abs((h.radius_dev_um or med) - med))
        d = (med if worst.radius_dev_um is None else worst.radius_dev_um) - med
        bad = abs(d) > tol.sphere_radius_spread_um
        out.append(Check(f"sphere radius, ball {worst.ball} pose {worst.pose}", d, None,
                         "µm", "ERROR" if bad else "PASS",
                         f"spread limit {tol.sphere_radius_spread_um:g} µm around the run median"
                         + (": dirt, chip, damaged ball or early trigger" if bad else "")))
    forms = [(h.form_rms_um, h) for h in health if h.form_rms_um is not None]
    if tol.sphere_form_um is not None and forms:
        form, h = max(forms, key=lambda x: x[0])
        bad = form > tol.sphere_form_um
        out.append(Check(f"sphere form, ball {h.ball} pose {h.pose}",
                         form, None, "µm", "ERROR" if bad else "PASS",
                         f"health limit {tol.sphere_form_um:g} µm"))
    stab = analysis.stability
    if tol.run_drift_um is not None and stab is not None:
        w, span = stab.worst, stab.span_min
        bad = stab.max_shift_um > tol.run_drift_um
        over = f" over {duration_text(span * 60)}" if span is not None else ""
        out.append(Check(f"revisit shift, ball {w.ball} pose {w.pose}",
                         float(stab.max_shift_um), None, "µm", "ERROR" if bad else "PASS",
                         f"health limit {tol.run_drift_um:g} µm{over}"
                         + (": machine or artefact not thermally stable during the run (warm "
                            "up, check the ball is tight) — measurement not trusted"
                            if bad else "")))
    # the residual last: a bad sphere (named above) is usually what inflates it
    rms = analysis.residual_rms_um
    if tol.residual_rms_um is not None and rms is not None:
        ok = rms <= tol.residual_rms_um
        out.append(Check("residual RMS", float(rms), None, "µm", "PASS" if ok else "ERROR",
                         f"health limit {tol.residual_rms_um:g} µm: measurement not trusted"
                         if not ok else f"health limit {tol.residual_rms_um:g} µm"))
    return out


def _outliers(analysis: Analysis) -> list[Check]:
    """A ball visit with one touch off the sphere the rest of the run predicts (a chip, dirt, a
    coolant drop, a bad trigger; ``identification.outliers``) biases its centre by several µm:
    ERROR naming the visit and the size, unless a clean re-probe replaced it. One check per
    ball visit of the plan, its re-probes folded in."""
    slots: dict[tuple[int, str, int], list] = {}
    for o in analysis.outliers or ():
        slots.setdefault((o.pose, o.ball, o.repeat % REPROBE_REPEAT_BASE), []).append(o)
    out = []
    for (pose, ball, repeat), found in sorted(slots.items()):
        found.sort(key=lambda o: o.repeat)
        o = found[0]
        rep = f" repeat {repeat}" if repeat else ""
        what = f"measurement outlier, ball {ball} pose {pose}{rep} touch {o.touch}"
        size = float(o.size_um) if o.size_um is not None else float("nan")
        if o.status == "unrepaired":
            again = [x for x in found[1:] if x.repeat >= REPROBE_REPEAT_BASE]
            why = (f"re-probed {len(again)}×, the fault came back ("
                   + ", ".join(f"touch {x.touch} {x.size_um or 0:+.1f} µm" for x in again)
                   + "): a chip stuck on the ball, a burr or a dent" if again else
                   "not re-probed")
            out.append(Check(what, size, None, "µm", "ERROR",
                             f"one touch off the sphere the rest of the run predicts (robust "
                             f"z {o.score or 0:.0f}; chip, dirt, coolant or a bad trigger), "
                             f"{why} — measurement not trusted; clean the ball and run again"))
        elif o.status == "repaired":
            out.append(Check(what, size, None, "µm", "PASS",
                             f"repaired: re-probed, the clean visit (repeat "
                             f"{o.replaced_by_repeat}) is used"))
        else:
            out.append(Check(what, size, None, "µm", "PASS",
                             "a re-probe that met a fault; the clean first visit is used"))
    return out


def _unit(unit: str) -> str:
    return {"um": "µm", "urad": "µrad"}.get(unit, unit)
