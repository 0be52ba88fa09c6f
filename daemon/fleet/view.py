"""The fleet page's HTML as text (no I/O): the fleet table (last verdict, date, age, stale
flag), a machine's run list and its per-link trend as inline SVG, one chart per link with
its own axis in its unit (µrad rotations and µm translations never share an axis)."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping, Sequence
from html import escape
from typing import Any
from urllib.parse import quote

from contracts.temperatures import channel_text
from daemon.analysis.figures import DEFINITIONS, LABELS, VOLUMETRIC
from daemon.analysis.judge import NO_BASELINE
from daemon.fleet.chart import LEFT_PX, RIGHT_PX, WIDTH_PX, Frame, padded
from daemon.reports.index_scatter import index_scatter_text

UNITS = {"urad": "µrad", "um": "µm"}
VERDICTS = ("PASS", "WARN", "FAIL", "ERROR")
_ENDED = ("DONE", "FAILED", "ABORTED", "INTERRUPTED")  # a run in no other state is running
# ended without a verdict: an error; DONE without one is a map job (it maps, it does not judge)
_ERROR_ENDS = ("FAILED", "ABORTED", "INTERRUPTED")
_H, _T, _B = 150, 10, 26  # the trend chart's height, top and bottom margins, px


def _e(x: Any) -> str:
    return escape("" if x is None else str(x), quote=True)


MAX_CHART = 1e12  # µm or µrad (1000 km): beyond, a stored value is garbage, not a deviation
MAX_TIME_S = 32503680000.0  # year 3000: dates and the chart's time axis stay defined


def finite(x: Any, bound: float = math.inf) -> float | None:
    """A stored number as a float, or None when it is missing, not a number, NaN, infinite,
    an integer too large for a float or beyond ``bound``: the store is written by daemons of
    other versions and by hand, and one bad cell must cost its chart a point or a line, never
    the page (a 500; the fuzz found 1e16 s and 1e16 µm dividing by zero)."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return None
    try:
        v = float(x)
    except OverflowError:  # an int beyond 1.8e308
        return None
    return v if math.isfinite(v) and abs(v) <= bound else None


def when(t: Any) -> str:
    """A date the shop reads: local time with its zone."""
    t = finite(t, MAX_TIME_S)
    try:
        return "—" if t is None else time.strftime("%Y-%m-%d %H:%M %Z", time.localtime(t))
    except (OverflowError, ValueError, OSError):  # a date the platform cannot show
        return "—"


def age_text(age_s: float | None) -> str:
    if age_s is None:
        return "—"
    m = max(0, int(age_s // 60))
    if m < 60:
        return f"{m} min"
    h, m = divmod(m, 60)
    if h < 48:
        return f"{h} h {m:02d} min"
    return f"{h // 24} d {h % 24} h"


def fleet_rows(fleet: Sequence[Mapping[str, Any]], now: float, stale_after_h: float
               ) -> list[dict[str, Any]]:
    """The table's rows: age from the verdict's end (its start if it never ended); stale when
    older than ``stale_after_h`` or when a machine has no verdict at all."""
    out = []
    for m in fleet:
        t = finite(m.get("ended_at")) or finite(m.get("started_at"))
        age = None if t is None else now - t
        running = m.get("current_state") not in (None, *_ENDED)
        out.append({**m, "verdict_at": t, "age_s": age,
                    "stale": age is None or age > stale_after_h * 3600.0,
                    "running": running})
    return out


def _page(title: str, body: str, refresh_s: int | None = None) -> str:
    meta = f'<meta http-equiv="refresh" content="{refresh_s}">' if refresh_s else ""
    return ("<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{_e(title)}</title>{meta}"
            '<meta name="viewport" content="width=device-width, initial-scale=1">'
            '<link rel="stylesheet" href="/hmi.css"><link rel="stylesheet" href="/fleet.css">'
            f"</head><body class=\"fleet\">{body}</body></html>\n")


def _badge(verdict: str | None) -> str:
    v = verdict if verdict in VERDICTS else "ERROR"
    return f'<span class="badge {v}">{v}</span>' if verdict else '<span class="none">—</span>'


def fleet_page(rows: Sequence[Mapping[str, Any]], stale_after_h: float, note: str = "") -> str:
    head = ("<tr><th>Machine</th><th>Site</th><th>Dialect / transport</th><th>Last verdict"
            "</th><th>Date</th><th>Age</th><th>Now</th><th>Report</th></tr>")
    body = []
    for r in rows:
        name = _e(r["machine"])
        href = f"/machines/{quote(str(r['machine']), safe='')}"
        stale = ' <span class="stale-flag">STALE</span>' if r["stale"] else ""
        report = (f'<a class="report" href="/reports/{_e(r["run_id"])}.html">report</a>'
                  if r.get("has_report") else "—")
        now = (f'<span class="running">{_e(r["current_state"])}</span>' if r["running"]
               else "idle")
        body.append(
            f'<tr class="row{" stale" if r["stale"] else ""}" data-machine="{name}">'
            f'<td><a class="machine-link" href="{_e(href)}">{name}</a></td>'
            f'<td>{_e(r.get("site") or "")}</td>'
            f'<td>{_e(r.get("dialect") or "?")} / {_e(r.get("transport") or "?")}</td>'
            f'<td class="verdict-cell">{_badge(r.get("verdict"))}</td>'
            f'<td class="date">{_e(when(r["verdict_at"]))}</td>'
            f'<td class="age">{_e(age_text(r["age_s"]))}{stale}</td>'
            f'<td class="now">{now}</td><td>{report}</td></tr>')
    empty = ('<p class="empty">No machine has reported to this store yet.</p>'
             if not rows else "")
    counts = {v: sum(1 for r in rows if r.get("verdict") == v) for v in VERDICTS}
    stale_n = sum(1 for r in rows if r["stale"])
    summary = " · ".join(f"{v} {n}" for v, n in counts.items()) + f" · stale {stale_n}"
    html = (f'<header><h1>rumba fleet</h1><p class="sub">{len(rows)} machines · {summary} · '
            f"stale after {stale_after_h:g} h</p>{note}</header>"
            f'<main><table class="fleet-table"><thead>{head}</thead><tbody>'
            f'{"".join(body)}</tbody></table>{empty}</main>')
    return _page("rumba fleet", html, refresh_s=60)


def _limit(name: str, unit: str, limits: Any) -> dict[str, float] | None:
    """The link's warn / fail limits that are numbers (its own, else the unit's default)."""
    if not isinstance(limits, Mapping):
        return None
    links = limits.get("links")
    own = links.get(name) if isinstance(links, Mapping) else None
    lim = own or limits.get("default_urad" if unit == "urad" else "default_um")
    if not isinstance(lim, Mapping):
        return None
    out = {k: v for k in ("warn", "fail") if (v := finite(lim.get(k), MAX_CHART)) is not None}
    return out or None


def link_chart(name: str, unit: str, points: Sequence[tuple[float, float, str, str]],
               limit: Mapping[str, Any] | None) -> str:
    """One link's trend: ``points`` (time s, value, verdict, run id), its warn / fail lines
    (two-sided: the judge compares |value|) and a y axis labelled in ``unit``."""
    label = UNITS.get(unit, unit)
    vals = [p[1] for p in points]
    bounds = vals + [s * limit[k] for k in ("warn", "fail") for s in (1, -1)
                     if limit and k in limit]
    frame = Frame(_H, _T, _B, *padded(min(bounds), max(bounds)))
    y = frame.y
    t0, t1 = points[0][0], points[-1][0]
    span = (t1 - t0) or 1.0

    def x(t: float) -> float:
        return LEFT_PX + (WIDTH_PX - LEFT_PX - RIGHT_PX) * ((t - t0) / span if t1 > t0 else 0.5)

    parts = [frame.open({"class": "chart", "data-link": name, "data-unit": label},
                        f"{name} trend in {label}"),
             *frame.y_grid(), frame.y_label(label)]
    for k in ("warn", "fail"):
        if limit and limit.get(k) is not None:
            for s in (1, -1):
                yy = y(s * float(limit[k]))
                parts.append(f'<line class="limit {k}" data-limit="{k}" x1="{LEFT_PX}" '
                             f'x2="{WIDTH_PX - RIGHT_PX}" y1="{yy:.1f}" y2="{yy:.1f}"/>')
    if len(points) > 1:
        line = " ".join(f"{x(p[0]):.1f},{y(p[1]):.1f}" for p in points)
        parts.append(f'<polyline class="series" points="{line}"/>')
    for t, v, verdict, run_id in points:
        parts.append(f'<circle class="pt {_e(verdict)}" cx="{x(t):.1f}" cy="{y(v):.1f}" r="3">'
                     f"<title>{_e(run_id)} {_e(when(t))}: {v:.3g} {_e(label)} ({_e(verdict)})"
                     "</title></circle>")
    for t, anchor in ((t0, "start"), (t1, "end")):
        parts.append(f'<text class="tick" x="{x(t) if t1 > t0 else LEFT_PX:.1f}" y="{_H - 6}" '
                     f'text-anchor="{anchor}">{_e(time.strftime("%Y-%m-%d", time.localtime(t)))}'
                     "</text>")
    parts.append("</svg>")
    return "".join(parts)


def trend_charts(trend: Sequence[Mapping[str, Any]], limits: Mapping[str, Any]) -> str:
    """Per link one chart, rotations (µrad) in one section and translations (µm) in
    another, link order as the analysis gives it."""
    series: dict[str, dict[str, Any]] = {}
    for run in trend:
        links = run.get("links")
        for name, link in (links.items() if isinstance(links, Mapping) else ()):
            v = finite(link.get("value"), MAX_CHART) if isinstance(link, Mapping) else None
            t = finite(run.get("started_at"), MAX_TIME_S)
            if v is None or t is None:
                continue
            s = series.setdefault(name, {"unit": link.get("unit", ""), "points": []})
            s["points"].append((t, v, str(run["verdict"]),
                                str(run["run_id"])))
    out = []
    for unit, title in (("urad", "Rotations"), ("um", "Translations")):
        charts = [f'<figure class="link"><figcaption>{_e(n)} '
                  f'({len(s["points"])} runs)</figcaption>'
                  f'{link_chart(n, unit, s["points"], _limit(n, unit, limits))}</figure>'
                  for n, s in series.items() if s["unit"] == unit]
        if charts:
            out.append(f'<section class="unit" data-unit="{UNITS[unit]}"><h2>{title} — '
                       f'{UNITS[unit]}</h2>{"".join(charts)}</section>')
    return "".join(out) or '<p class="empty">No analysed run in this period.</p>'


def temperatures_text(temps: Any) -> str:
    """A run's temperature channels, "spindle 20.5 → 24.1 °C (+3.6 °C)": the text
    the report and the HMI print (contracts.temperatures.channel_text: a start not read is
    said, never filled in); a store written by hand or another version costs the cell, never
    the page."""
    if not isinstance(temps, Mapping):
        return ""
    return "; ".join(channel_text(str(name), t) for name, t in temps.items())


def drift_baseline(run: Mapping[str, Any]) -> str:
    """The baseline run the drift checks of ``run`` were judged against (from its
    verdict's checks), "drift not checked: no baseline", or "—" (no drift limits, no verdict)."""
    try:
        checks = json.loads(run.get("checks") or "[]")
        reasons = json.loads(run.get("reasons") or "[]")
    except (TypeError, ValueError):  # another version's row: the page stays up
        return "—"
    refs = sorted({str(c["reference_run"]) for c in checks if isinstance(c, dict)
                   and c.get("reference_run")})
    if refs:
        return "run " + ", ".join(refs)
    return NO_BASELINE if isinstance(reasons, list) and NO_BASELINE in reasons else "—"


def report_cell(run: Mapping[str, Any]) -> str:
    """The report's link; until it is there (written after the run's end) "being
    written", or why it was not — from the run's report job (migration 10), never its reason."""
    if run.get("has_report"):
        return f'<a class="report" href="/reports/{_e(run["id"])}.html">report</a>'
    if run.get("report_state") == "failed":
        why = str(run.get("report_error") or "see the daemon's log")
        return f'<span class="report-failed">report not written: {_e(why)}</span>'
    if run.get("report_state") == "writing":
        return '<span class="report-writing">report being written</span>'
    return "—"


def machine_page(name: str, machine: Mapping[str, Any] | None, runs: Sequence[Mapping[str, Any]],
                 trend: Sequence[Mapping[str, Any]], days: int) -> str:
    limits = (machine or {}).get("limits") or {}
    rows = "".join(
        f'<tr><td>{_e(r["id"])}</td><td>{_e(when(r["started_at"]))}</td>'
        f'<td>{_e(r["trigger"])}</td><td>{_e(r["state"])}</td>'
        f'<td>{_badge(r["verdict"] or ("ERROR" if r["state"] in _ERROR_ENDS else None))}</td>'
        f'<td>{_e(r["summary"])}</td><td>{_e(temperatures_text(r.get("temperatures")))}</td>'
        f'<td class="index-scatter">{_e(index_scatter_text(r.get("index_scatter")))}</td>'
        f'<td class="baseline">{_e(drift_baseline(r))}</td><td>{report_cell(r)}</td></tr>'
        for r in runs)
    desc = ("" if machine is None else
            f'{_e(machine.get("site"))} · {_e(machine.get("dialect"))} / '
            f'{_e(machine.get("transport"))}')
    against = (f'<p><a class="against-temperature" href="/machines/{_e(name)}/temperature">'
               "Link errors against temperature</a></p>"  # when a run has readings
               if any(r.get("temperatures") for r in runs) else "")
    html = (f'<header><p><a href="/">← fleet</a></p><h1>{_e(name)}</h1>'
            f'<p class="sub">{desc}</p></header><main>'
            f'<h2>Trend, last {days} days (limits: dashed amber warn, red fail)</h2>'
            f'{trend_charts(trend, limits)}'
            '<h2>Runs</h2><table class="runs"><thead><tr><th>Run</th><th>Started</th>'
            '<th>Trigger</th><th>State</th><th>Verdict</th><th>Summary</th>'
            '<th>Temperatures</th><th>Indexing repeatability</th><th>Drift baseline</th>'
            '<th>Report</th>'
            f"</tr></thead><tbody>{rows}</tbody></table>{against}"
            # the summary's figure is defined beside it, as on every surface
            f'<p class="definition">{_e(LABELS[VOLUMETRIC])}: {_e(DEFINITIONS[VOLUMETRIC])}.'
            "</p></main>")
    return _page(f"rumba fleet — {name}", html)
