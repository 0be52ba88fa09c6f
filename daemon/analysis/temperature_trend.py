"""A link error against a recorded temperature over a machine's runs: does
"EX0C move with the spindle temperature"? Each run gives one point, the channel's mean over the
run (start, every pose, end) and the link's identified value ± u; the straight line is fitted
by ordinary least squares with its slope's standard uncertainty from the residual scatter
(GUM: the run-to-run spread of a link, not only its within-run u, is what the slope must beat)
and Pearson's correlation coefficient r."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from contracts.temperatures import run_mean_c
from daemon.analysis.result import Analysis


@dataclass(frozen=True)
class TempPoint:
    run_id: str
    temperature_c: float
    value: float
    std: float | None


@dataclass(frozen=True)
class TempFit:
    """value ≈ intercept + slope·(T − mean T); ``slope_std`` None below 3 runs."""

    n: int
    r: float | None
    slope: float | None
    slope_std: float | None
    unit: str  # the link's unit per °C, e.g. "µm/°C"
    slope_u95: float | None = None  # expanded: Student's t(0.975, n − 2) · slope_std


    def text(self, link: str, channel: str) -> str:
        if self.slope is None or self.r is None:
            return f"{link} against {channel}: {self.n} runs with both, at least 3 needed"
        u = f" ± {self.slope_std:.3g}" if self.slope_std is not None else ""
        u95 = (f"; 95 %: ± {self.slope_u95:.3g}, Student's t with {self.n - 2} dof"
               if self.slope_u95 is not None else "")
        return (f"{link} against {channel}: r = {self.r:+.2f}, slope {self.slope:+.3g}{u} "
                f"{self.unit} (u, OLS from the residual scatter{u95}; {self.n} runs)")


def run_temperature(analysis: Analysis, channel: str) -> float | None:
    """The channel's temperature over the run (contracts.temperatures.run_mean_c): the mean the
    summary carries, or — a summary stored before it did — the same definition on its per-pose
    values, else its start and end."""
    t: dict[str, Any] | None = (analysis.temperatures or {}).get(channel)
    if not t:
        return None
    if "mean_c" in t:
        return None if t["mean_c"] is None else float(t["mean_c"])
    return run_mean_c([p.get("value_c") for p in t.get("per_pose", [])], t.get("start_c"),
                      t.get("end_c"))


def fleet_points(rows: Sequence[Mapping[str, Any]], link: str) -> tuple[list[TempPoint], str]:
    """One point per run from the fleet store's raw readings (daemon/store/pg_temperatures.py
    ``readings``): the same run temperature and link value as ``points``, for ``fit``."""
    out, unit = [], ""
    for row in rows:
        est = (row.get("links") or {}).get(link)
        temp = run_mean_c(row.get("pose_c") or [], row.get("start_c"), row.get("end_c"))
        if not isinstance(est, Mapping) or temp is None:
            continue
        value, std = est.get("value"), est.get("std")
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            continue  # another version's row costs its point, never the view
        unit = "µrad" if est.get("unit") == "urad" else "µm"
        out.append(TempPoint(str(row["run_id"]), temp, float(value),
                             float(std) if isinstance(std, (int, float)) and math.isfinite(std)
                             else None))
    return out, unit


def points(trend: list[Any], link: str, channel: str) -> tuple[list[TempPoint], str]:
    """One point per run (``store.trend`` rows) with both the link and the channel; the unit."""
    out, unit = [], ""
    for row in trend:
        est = row.analysis.links.get(link)
        temp = run_temperature(row.analysis, channel)
        if est is None or temp is None:
            continue
        unit = "µrad" if est.unit == "urad" else "µm"
        out.append(TempPoint(row.run_id, temp, float(est.value), est.std))
    return out, unit


def fit(pts: list[TempPoint], unit: str) -> TempFit:
    n = len(pts)
    if n < 3:
        return TempFit(n, None, None, None, f"{unit}/°C")
    mt = sum(p.temperature_c for p in pts) / n
    mv = sum(p.value for p in pts) / n
    sxx = sum((p.temperature_c - mt) ** 2 for p in pts)
    syy = sum((p.value - mv) ** 2 for p in pts)
    sxy = sum((p.temperature_c - mt) * (p.value - mv) for p in pts)
    if sxx <= 0:  # every run at one temperature: no slope to speak of
        return TempFit(n, None, None, None, f"{unit}/°C")
    slope = sxy / sxx
    r = sxy / math.sqrt(sxx * syy) if syy > 0 else 0.0
    ssr = max(syy - slope * sxy, 0.0)
    u = math.sqrt(ssr / (n - 2) / sxx)
    from scipy.stats import t  # only here: the CLI's other commands stay fast

    return TempFit(n, r, slope, u, f"{unit}/°C", float(t.ppf(0.975, n - 2)) * u)
