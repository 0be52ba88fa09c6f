"""The run report: one self-contained HTML file (plots embedded as base64 PNG) and a JSON file
with the same numbers. Plots as in DESIGN.md: distortion vectors per pose (xy, yz, xz, 3D; thesis
Fig 3.10), relocalisation vs local distortion per pose (thesis §4.4), link errors with 2u bars
and tolerance lines, and the trend over past runs of the machine.
"""

from __future__ import annotations

import base64
import io
import json
import math
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import jinja2
import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from daemon.analysis_result import Analysis
from daemon.judge import Judgement, Limit, Tolerances, volumetric_max_um
from daemon.safepath import contained_path
from daemon.store import RunRow, TrendPoint, validate_run_id

VERDICT_COLOURS = {"PASS": "#1b873f", "WARN": "#c77700", "FAIL": "#c62828", "ERROR": "#6a1b9a"}


def _png(fig: Figure) -> str:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def plot_distortion(analysis: Analysis,
                    centres: dict[tuple[int, str], Sequence[float]]) -> str | None:
    """Arrows of the volumetric distortion (setup errors removed) at every measured centre
    (``centres``: (pose, ball) → x y z mm), magnified; one colour per pose (thesis Fig 3.10)."""
    vol = [v for v in analysis.volumetric if (v.pose, v.ball) in centres]
    if not vol:
        return None
    pts = np.array([centres[(v.pose, v.ball)] for v in vol])
    err = np.array([v.error_um for v in vol])
    poses = np.array([v.pose for v in vol])
    span = float(np.ptp(pts, axis=0).max()) or 1.0
    emax = float(np.linalg.norm(err, axis=1).max()) or 1.0
    mag = 0.15 * span / (emax * 1e-3)  # the longest arrow is 15 % of the cloud
    vec = err * 1e-3 * mag
    fig = Figure(figsize=(12, 9), layout="constrained")
    cmap = matplotlib.colormaps["tab20"]
    colours = [cmap(int(p) % 20) for p in poses]
    for k, (i, j, name) in enumerate([(0, 1, "XY"), (1, 2, "YZ"), (0, 2, "XZ")]):
        ax = fig.add_subplot(2, 2, k + 1)
        ax.scatter(pts[:, i], pts[:, j], s=8, c=colours)
        ax.quiver(pts[:, i], pts[:, j], vec[:, i], vec[:, j], color=colours, angles="xy",
                  scale_units="xy", scale=1, width=0.004)
        ax.set_xlabel(f"{name[0]} / mm")
        ax.set_ylabel(f"{name[1]} / mm")
        ax.set_title(f"{name} plane")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    ax3 = fig.add_subplot(2, 2, 4, projection="3d")
    ax3.quiver(pts[:, 0], pts[:, 1], pts[:, 2], vec[:, 0], vec[:, 1], vec[:, 2],
               colors=colours, arrow_length_ratio=0.2)
    ax3.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=6, c=colours)
    ax3.set_xlabel("X / mm")
    ax3.set_ylabel("Y / mm")
    ax3.set_zlabel("Z / mm")
    fig.suptitle(f"Volumetric distortion per pose (setup errors removed), arrows ×{mag:.0f}; "
                 f"max {emax:.1f} µm")
    return _png(fig)


def plot_cluster(analysis: Analysis) -> str | None:
    """Per pose: |linear relocalisation| (µm), |angular relocalisation| (µrad) and the largest
    local distortion (µm) — rotary errors relocate, linear-axis errors also distort."""
    cl = [c for c in analysis.cluster if c.linear_um is not None]
    if not cl:
        return None
    x = np.arange(len(cl))
    lin = [math.hypot(*c.linear_um) for c in cl]  # type: ignore[misc]
    ang = [math.hypot(*c.angular_urad) for c in cl]  # type: ignore[misc]
    loc = [max((math.hypot(*v) for v in c.local_um.values()), default=0.0)  # type: ignore[misc]
           for c in cl]
    labels = [f"{c.pose}\nB{c.b_deg:g} C{c.c_deg:g}" for c in cl]
    fig = Figure(figsize=(12, 4.5), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    w = 0.28
    ax.bar(x - w, lin, w, label="linear relocalisation |D| / µm", color="#1565c0")
    ax.bar(x, ang, w, label="angular relocalisation |R| / µrad", color="#6a1b9a")
    ax.bar(x + w, loc, w, label="local distortion max / µm", color="#ef6c00")
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_title("Relocalisation vs local distortion per pose (cluster analysis, thesis §4.4)")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return _png(fig)


def _limit_for(name: str, unit: str, tol: Tolerances | None) -> Limit | None:
    if tol is None:
        return None
    return tol.links.get(name) or (
        tol.default_rotation_urad if unit == "urad" else tol.default_translation_um)


def plot_links(analysis: Analysis, tol: Tolerances | None) -> str | None:
    links = analysis.links
    if not links:
        return None
    groups = [("urad", "Rotations / µrad"), ("um", "Translations / µm")]
    fig = Figure(figsize=(12, 4.5), layout="constrained")
    n = sum(1 for u, _ in groups if any(v.unit == u for v in links.values()))
    k = 0
    for unit, title in groups:
        names = [nm for nm, v in links.items() if v.unit == unit]
        if not names:
            continue
        k += 1
        ax = fig.add_subplot(1, n, k)
        vals = [links[nm].value for nm in names]
        errs = [2 * (links[nm].std or 0.0) for nm in names]
        x = np.arange(len(names))
        ax.errorbar(x, vals, yerr=errs, fmt="o", color="#0d47a1", capsize=5,
                    label="estimate ± 2u")
        for i, nm in enumerate(names):
            lim = _limit_for(nm, unit, tol)
            for val, colour, style in ((lim.warn, "#c77700", "--"), (lim.fail, "#c62828", "-")) \
                    if lim else ():
                if val is not None:
                    ax.hlines([val, -val], i - 0.35, i + 0.35, colors=colour, linestyles=style)
        ax.axhline(0, color="grey", lw=0.8)
        ax.set_xticks(x, names)
        ax.set_title(title + "  (orange: warn, red: fail)")
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle("Identified link errors (ISO 230-1)")
    return _png(fig)


def plot_trend(trend: list[TrendPoint]) -> str | None:
    if len(trend) < 2:
        return None
    fig = Figure(figsize=(12, 6), layout="constrained")
    ax1 = fig.add_subplot(2, 1, 1)
    ax2 = fig.add_subplot(2, 1, 2, sharex=ax1)
    x = np.arange(len(trend))
    names = sorted({n for t in trend for n in t.analysis.links})
    for nm in names:
        ys = [t.analysis.links[nm].value if nm in t.analysis.links else np.nan for t in trend]
        unit = next(t.analysis.links[nm].unit for t in trend if nm in t.analysis.links)
        ax1.plot(x, ys, marker="o", ms=3, label=f"{nm} / {'µrad' if unit == 'urad' else 'µm'}")
    ax1.set_title("Link errors over past runs")
    ax1.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax1.grid(alpha=0.3)
    vmax = [volumetric_max_um(t.analysis) or np.nan for t in trend]
    ax2.plot(x, vmax, color="grey", lw=1)
    ax2.scatter(x, vmax, c=[VERDICT_COLOURS.get(t.verdict, "grey") for t in trend], zorder=3)
    ax2.set_ylabel("max distortion / µm")
    ax2.set_title("Volumetric distortion max norm (dot colour = verdict)")
    ax2.set_xticks(x, [time.strftime("%m-%d\n%H:%M", time.localtime(t.started_at))
                       for t in trend], fontsize=7)
    ax2.grid(alpha=0.3)
    return _png(fig)


_TEMPLATE = jinja2.Environment(autoescape=True).from_string("""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>rumba run {{ run.id }}</title>
<style>
body{font-family:system-ui,sans-serif;margin:2em;max-width:1200px;color:#222}
.badge{display:inline-block;padding:.3em .8em;border-radius:.3em;color:#fff;font-size:1.6em;
font-weight:bold;background:{{ colour }}}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:.25em .6em;
text-align:right}th{background:#f3f3f3}td.l,th.l{text-align:left}
.PASS{color:#1b873f}.WARN{color:#c77700;font-weight:bold}.FAIL{color:#c62828;font-weight:bold}
img{max-width:100%;border:1px solid #eee;margin:.5em 0}small{color:#666}
</style></head><body>
<h1>Machine {{ run.machine }} — run {{ run.id }}</h1>
<p><span class="badge">{{ verdict.status if verdict else run.state }}</span>
&nbsp; {{ run.summary }}</p>
<p><small>started {{ started }} by {{ run.trigger }}; plan {{ run.plan }}, artefact
{{ run.artefact }}, dialect {{ run.dialect }}; {{ analysis.touches }} touches;
residual RMS {{ '%.2f' % analysis.residual_rms_um }} µm; condition number
{{ '%.3g' % analysis.condition_number }}{% if analysis.reference_run %}; drift reference: run
{{ analysis.reference_run }}{% endif %}</small></p>
{% if verdict and verdict.reasons %}<h2>Reasons</h2><ul>
{% for r in verdict.reasons %}<li>{{ r }}</li>{% endfor %}</ul>{% endif %}
{% if verdict %}<h2>Checks</h2><table><tr><th class="l">quantity</th><th>value</th><th>u</th>
<th class="l">unit</th><th class="l">limit</th><th class="l">status</th></tr>
{% for c in verdict.checks %}<tr><td class="l">{{ c.quantity }}</td>
<td>{{ '%+.2f' % c.value if c.value == c.value else '—' }}</td>
<td>{{ '%.2f' % c.std if c.std else '' }}</td><td class="l">{{ c.unit }}</td>
<td class="l">{{ c.limit }}</td><td class="l {{ c.status }}">{{ c.status }}</td></tr>
{% endfor %}</table>{% endif %}
<h2>Link errors</h2><table><tr><th class="l">ISO 230-1</th><th>value</th><th>u (k=1)</th>
<th class="l">unit</th></tr>{% for n, v in analysis.links|dictsort %}<tr><td class="l">{{ n }}</td>
<td>{{ '%+.2f' % v.value }}</td><td>{{ '%.2f' % v.std }}</td>
<td class="l">{{ 'µrad' if v.unit == 'urad' else 'µm' }}</td></tr>{% endfor %}</table>
<p><small>Not observable: {{ analysis.unobservable|join(', ') or 'nothing' }}.</small></p>
{% for title, img in plots %}{% if img %}<h2>{{ title }}</h2>
<img alt="{{ title }}" src="data:image/png;base64,{{ img }}">{% endif %}{% endfor %}
<h2>Setup errors</h2><table><tr><th class="l">item</th><th>dx / µm</th><th>dy / µm</th>
<th>dz / µm</th><th>u / µm</th></tr>
<tr><td class="l">probe</td>{% for x in analysis.setup.probe.value %}<td>{{ '%+.1f' % x }}</td>
{% endfor %}<td>{{ '%.2f' % (analysis.setup.probe.std|max) }}</td></tr>
{% for b, v in analysis.setup.balls|dictsort %}<tr><td class="l">ball {{ b }}</td>
{% for x in v.value %}<td>{{ '%+.1f' % x }}</td>{% endfor %}
<td>{{ '%.2f' % (v.std|max) }}</td></tr>{% endfor %}</table>
{% if analysis.validation %}<h2>Validation on held-out poses</h2><p>RMS
{{ '%.1f' % analysis.validation.rms_before_um }} → {{ '%.1f' % analysis.validation.rms_after_um }}
µm, max {{ '%.1f' % analysis.validation.max_before_um }} →
{{ '%.1f' % analysis.validation.max_after_um }} µm; explained
{{ '%.0f' % (100 * analysis.validation.explained_fraction) }} %.</p>{% endif %}
<h2>Probe and ball health</h2><p>Largest sphere-fit radius deviation
{{ '%.1f' % health_rad }} µm, largest form residual {{ '%.2f' % health_form }} µm.</p>
{% if analysis.stability %}<p>Stability during the run (poses probed again): largest
ball-centre shift between the first and last visit
{{ '%.1f' % analysis.stability.max_shift_um }} µm (ball {{ analysis.stability.worst.ball }},
pose {{ analysis.stability.worst.pose }}{% if analysis.stability.span_min is not none %}, over
{{ '%.1f' % analysis.stability.span_min }} min{% endif %}).</p>{% endif %}
{% if analysis.warnings %}<h2>Warnings</h2><ul>{% for w in analysis.warnings %}<li>{{ w }}</li>
{% endfor %}</ul>{% endif %}
<p><small>rumba-cnc report generated {{ generated }}; numbers also in {{ json_name }}.</small></p>
</body></html>
""")


def verdict_doc(judgement: Judgement | None) -> dict[str, Any] | None:
    """The verdict as the report shows it and writes it to its JSON (the journal's verdict
    record at report time: written back later, after the report)."""
    if judgement is None:
        return None
    return {"status": judgement.status, "reasons": list(judgement.reasons),
            "checks": [c.as_dict() for c in judgement.checks], "written_back": False}


def build(run: RunRow, analysis: Analysis, judgement: Judgement | None,
          centre_rows: Iterable[Sequence[Any]], trend: list[TrendPoint],
          tol: Tolerances | None) -> tuple[str, dict[str, Any]]:
    """(HTML text, JSON document) for one run: its record, analysis, judgement, centre rows
    (pose, ball, b, c, x, y, z, …) and the trend of its machine (oldest first)."""
    verdict = verdict_doc(judgement)
    centres = {(c[0], c[1]): c[4:7] for c in centre_rows}
    plots = [
        ("Volumetric distortion (thesis Fig 3.10)", plot_distortion(analysis, centres)),
        ("Relocalisation vs local distortion", plot_cluster(analysis)),
        ("Link errors", plot_links(analysis, tol)),
        ("Trend over past runs", plot_trend(trend)),
    ]
    health = analysis.health
    doc = {
        "run": {k: getattr(run, k) for k in ("id", "machine", "trigger", "state", "reason",
                                               "plan", "artefact", "dialect", "touch_total",
                                               "started_at", "ended_at", "summary")},
        "verdict": verdict, "analysis": analysis.to_json(),
        "trend": [{"run_id": t.run_id, "started_at": t.started_at, "verdict": t.verdict,
                   "volumetric_max_um": volumetric_max_um(t.analysis),
                   "links": {k: v.value for k, v in t.analysis.links.items()}}
                  for t in trend],
    }
    html = _TEMPLATE.render(
        run=run, verdict=verdict, analysis=analysis, plots=plots,
        colour=VERDICT_COLOURS.get(verdict["status"] if verdict else "ERROR", "#555"),
        started=time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(run.started_at)),
        generated=time.strftime("%Y-%m-%d %H:%M:%S"), json_name=f"{run.id}.json",
        health_rad=max((abs(h.radius_dev_um or 0.0) for h in health), default=0.0),
        health_form=max((h.form_rms_um or 0.0 for h in health), default=0.0))
    return html, doc


def write_report(reports_dir: Path, run: RunRow, analysis: Analysis,
                 judgement: Judgement | None, centre_rows: Iterable[Sequence[Any]],
                 trend: list[TrendPoint], tol: Tolerances | None = None) -> tuple[Path, Path]:
    """Write ``<reports_dir>/<run id>.html`` and ``.json`` from what the caller holds (no
    journal access); returns both paths. The run id names the files: it is checked, and both
    paths are proven to stay in ``reports_dir``."""
    run_id = validate_run_id(run.id)
    html, doc = build(run, analysis, judgement, centre_rows, trend, tol)
    reports_dir = Path(reports_dir)
    reports_dir.mkdir(parents=True, exist_ok=True)
    # after mkdir, so that the containment check sees the real directory and its symlinks
    html_path = contained_path(reports_dir, f"{run_id}.html")
    json_path = contained_path(reports_dir, f"{run_id}.json")
    json_path.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    html_path.write_text(html, encoding="utf-8")
    return html_path, json_path
