"""A machine's trend as numbers: per identified link error (and the volumetric distortion) its
unit, its value and uncertainty run by run, and the tolerance that applies to it — the one
source of the report's trend plot and the HMI's trend chart."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from daemon.analysis.judge import volumetric_max_um
from daemon.machines.tolerances import Limit, Tolerances
from daemon.store.journal import TrendPoint

UNITS = {"urad": "µrad", "um": "µm"}
VOLUMETRIC = "volumetric max"


def limit_for(name: str, unit: str, tol: Tolerances | None) -> Limit | None:
    """The limit the judge applies to link ``name`` (``unit`` "um" / "urad"): its own, else the
    default of its kind."""
    if tol is None:
        return None
    return tol.links.get(name) or (
        tol.default_rotation_urad if unit == "urad" else tol.default_translation_um)


def _num(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def trend_series(trend: Sequence[TrendPoint], tol: Tolerances | None) -> dict[str, Any]:
    """``{"runs": [{id, started_at, verdict}], "series": [{name, unit, values, std, warn,
    fail, two_sided}]}``, oldest run first; rotations (µrad), then translations (µm), then the
    volumetric distortion's largest norm (µm, one-sided). A run without a link has None."""
    units: dict[str, str] = {}
    for t in trend:
        for n, v in t.analysis.links.items():
            units.setdefault(n, v.unit)
    order = sorted(units, key=lambda n: (units[n] != "urad", n))
    series = []
    for n in order:
        lim = limit_for(n, units[n], tol)
        vals = [t.analysis.links.get(n) for t in trend]
        series.append({"name": n, "unit": UNITS.get(units[n], units[n]),
                       "values": [_num(v.value) if v else None for v in vals],
                       "std": [_num(v.std) if v else None for v in vals],
                       "warn": lim.warn if lim else None, "fail": lim.fail if lim else None,
                       "two_sided": True})
    vlim = tol.volumetric_max_um if tol else None
    vol = [_num(volumetric_max_um(t.analysis)) for t in trend]
    if any(v is not None for v in vol):
        series.append({"name": VOLUMETRIC, "unit": "µm", "values": vol,
                       "std": [None] * len(vol), "warn": vlim.warn if vlim else None,
                       "fail": vlim.fail if vlim else None, "two_sided": False})
    return {"runs": [{"id": t.run_id, "started_at": t.started_at, "verdict": t.verdict}
                     for t in trend], "series": series}
