"""The audit fields of a report (what an auditor asks of a measurement besides its numbers) and
the way the HTML and the PDF print them; "not recorded" where nobody gave them."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any

from daemon.analysis.result import Analysis
from daemon.analysis.verdict_text import duration_text
from daemon.reports import temperatures
from daemon.store.journal import RunRow

NOT_RECORDED = "not recorded"


@dataclass(frozen=True)
class Audit:
    """What an auditor asks of a measurement besides its numbers; None = not recorded."""

    machine_serial: str | None = None  # machine YAML ``serial``
    operator: str | None = None  # daemon.yaml ``machines[].operator``
    artefact_certificate: str | None = None  # artefact YAML ``calibration``
    artefact_calibrated_on: str | None = None  # ISO date
    artefact_laboratory: str | None = None
    temperature_c: float | None = None  # no sensor is read yet: always None today
    # what QA asks besides
    probe: str | None = None  # machine YAML ``probe`` + the plan's stylus diameter
    balls: str | None = None  # the artefact's ball diameters
    baseline: str | None = None  # the drift baseline (``store.baselines``), None: none set
    decision_rule: str | None = None  # ``judge.decision_rule``
    # every location error of the machine: "EX0C — X offset of the C axis line, Siemens …"
    link_names: dict[str, str] = field(default_factory=dict)


def audit_of(setup: Any, baseline: Any = None) -> Audit:
    """The audit fields of a machine's configuration (``machines.setup.MachineSetup``) and
    its drift baseline (``store.baselines.Baseline``, None: none set)."""
    from daemon.analysis.judge import decision_rule

    cal = getattr(getattr(setup, "artefact_file", None), "calibration", None)
    return Audit(machine_serial=getattr(setup.machine_file, "serial", None),
                 operator=getattr(setup, "operator", None),
                 artefact_certificate=cal.certificate if cal else None,
                 artefact_calibrated_on=cal.date.isoformat() if cal else None,
                 artefact_laboratory=cal.laboratory if cal else None,
                 probe=_probe(setup), balls=_balls(setup),
                 baseline=baseline.describe() if baseline is not None else None,
                 decision_rule=decision_rule(setup.tolerances.coverage_k),
                 link_names=_link_names(setup))


def _link_names(setup: Any) -> dict[str, str]:
    """Plain name and the controller's own term (its ``controller_kinematics`` family and
    address) of each location error of the machine."""
    from daemon.analysis.figures import link_label
    from daemon.compensation.propose import spec_of

    try:
        spec = spec_of(setup)
    except ValueError:  # refused when the configuration was loaded; no term then
        spec = None
    return {n: link_label(n, spec) for n in setup.machine.location_error_names()}


def _probe(setup: Any) -> str | None:
    plan = getattr(setup, "plan", None)
    rec = getattr(setup.machine_file, "probe", None)
    parts = [f"stylus diameter {plan.stylus_diameter_mm:g} mm (plan {plan.name})"] if plan \
        else []
    if rec is not None:
        who = " ".join(x for x in (rec.model, rec.serial and f"serial {rec.serial}") if x)
        if who:
            parts.insert(0, who)
        parts.append(f"qualified on {rec.qualified_on.isoformat()}"
                     + (f" by {rec.qualified_by}" if rec.qualified_by else ""))
    else:
        parts.append(f"qualification {NOT_RECORDED} (machine file: probe.qualified_on)")
    return ", ".join(parts) or None


def _balls(setup: Any) -> str | None:
    af = getattr(setup, "artefact_file", None)
    if af is None:
        return None
    return ", ".join(f"{b.id} ⌀{(b.ball_diameter_mm or af.ball_diameter_mm):g} mm"
                     for b in af.balls)


def local_time(t: float | None) -> str:
    """ISO-like local time with its UTC offset, e.g. ``2026-03-14 06:02:11 +0100``."""
    return "—" if t is None else time.strftime("%Y-%m-%d %H:%M:%S %z", time.localtime(t))


def software_version() -> str:
    try:
        return metadata.version("rumba-cnc")
    except metadata.PackageNotFoundError:
        return "unknown"


def _started_by(run: RunRow) -> str:
    """A person's name with the way in ("Anna Berg (HMI)"), else the trigger and that no
    person was recorded (the controller's request, the CAN panel, a script)."""
    person = getattr(run, "started_by", "")
    via = {"hmi": "HMI", "cli": "CLI", "cnc": "CNC request", "can": "CAN panel"}.get(
        run.trigger, run.trigger)
    return f"{person} ({via})" if person else f"{via} (no person recorded)"


def audit_rows(run: RunRow, audit: Audit, analysis: Analysis) -> list[tuple[str, str]]:
    """(field, value) as the HTML and the PDF print them."""
    cal = NOT_RECORDED
    if audit.artefact_certificate:
        cal = (f"certificate {audit.artefact_certificate} of "
               f"{audit.artefact_calibrated_on or '?'}"
               + (f", {audit.artefact_laboratory}" if audit.artefact_laboratory else ""))
    elif not analysis.scale_um_per_m:
        cal += " (the method needs none: the artefact is estimated with the machine)"
    temp = (f"{audit.temperature_c:.1f} °C" if audit.temperature_c is not None
            else temperatures.audit_text(analysis)  # the run's channels
            or f"{NOT_RECORDED} (no temperature sensor connected)")
    # a live run is reported before it ends: its span so far is the probing and the analysis
    span = (run.ended_at or time.time()) - run.started_at
    return [
        ("Machine", f"{run.machine} ({analysis.topology})"),
        ("Machine serial number", audit.machine_serial or NOT_RECORDED),
        ("Operator", audit.operator or NOT_RECORDED),
        ("Started by", _started_by(run)),
        ("Measured", f"{local_time(run.started_at)}, for {duration_text(span)}"),
        ("Artefact", run.artefact or analysis.artefact),
        ("Artefact calibration", cal),
        ("Temperature", temp),
        ("Probe", audit.probe or NOT_RECORDED),
        ("Balls", audit.balls or NOT_RECORDED),
        ("Drift baseline", audit.baseline or "none set: drift not checked (rumba baseline set)"),
        ("Plan, dialect", f"{run.plan}, {run.dialect}"),
        ("Software", f"rumba-cnc {software_version()}"),
    ]
