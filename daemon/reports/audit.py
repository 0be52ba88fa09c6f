"""The audit fields of a report (what an auditor asks of a measurement besides its numbers) and
the way the HTML and the PDF print them; "not recorded" where nobody gave them."""

from __future__ import annotations

import time
from dataclasses import dataclass
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


def audit_of(setup: Any) -> Audit:
    """The audit fields of a machine's configuration (``machines.setup.MachineSetup``)."""
    cal = getattr(getattr(setup, "artefact_file", None), "calibration", None)
    return Audit(machine_serial=getattr(setup.machine_file, "serial", None),
                 operator=getattr(setup, "operator", None),
                 artefact_certificate=cal.certificate if cal else None,
                 artefact_calibrated_on=cal.date.isoformat() if cal else None,
                 artefact_laboratory=cal.laboratory if cal else None)


def local_time(t: float | None) -> str:
    """ISO-like local time with its UTC offset, e.g. ``2026-03-14 06:02:11 +0100``."""
    return "—" if t is None else time.strftime("%Y-%m-%d %H:%M:%S %z", time.localtime(t))


def software_version() -> str:
    try:
        return metadata.version("rumba-cnc")
    except metadata.PackageNotFoundError:
        return "unknown"


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
            else temperatures.audit_text(analysis)  # issue 22: the run's channels
            or f"{NOT_RECORDED} (no temperature sensor connected)")
    # a live run is reported before it ends: its span so far is the probing and the analysis
    span = (run.ended_at or time.time()) - run.started_at
    return [
        ("Machine", f"{run.machine} ({analysis.topology})"),
        ("Machine serial number", audit.machine_serial or NOT_RECORDED),
        ("Operator", audit.operator or NOT_RECORDED),
        ("Started by", run.trigger),
        ("Measured", f"{local_time(run.started_at)}, for {duration_text(span)}"),
        ("Artefact", run.artefact or analysis.artefact),
        ("Artefact calibration", cal),
        ("Temperature", temp),
        ("Plan, dialect", f"{run.plan}, {run.dialect}"),
        ("Software", f"rumba-cnc {software_version()}"),
    ]
