"""The run report: one self-contained HTML file (plots embedded as base64 PNG, a print layout),
a JSON file with the same numbers, and a PDF of one or two A4 pages for filing
(``daemon.reports.pdf``) — all three from the same inputs. Plots as in DESIGN.md (distortion
vectors, relocalisation vs local distortion, link errors with limits, trend): ``plots``.
The verdict comes with a plain-language next step and the audit fields (machine serial,
operator, artefact calibration, temperature), "not recorded" where nobody gave them.
"""

from __future__ import annotations

import base64
import json
import time
from collections.abc import Iterable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import jinja2

from daemon.analysis.figures import LINK_DEFINITION, figures_json, run_figures
from daemon.analysis.judge import Judgement, volumetric_max_um
from daemon.analysis.result import Analysis
from daemon.analysis.verdict_text import advice, duration_text
from daemon.machines.tolerances import Tolerances
from daemon.reports.audit import Audit, audit_of, audit_rows, local_time
from daemon.reports.compensation import CompensationView
from daemon.reports.index_scatter import index_scatter_doc
from daemon.reports.pdf import write_pdf
from daemon.reports.plots import (
    VERDICT_COLOURS,
    draw_cluster,
    draw_distortion,
    draw_links,
    draw_trend,
    png,
)
from daemon.reports.temperatures import table_rows as temperature_rows
from daemon.safepath import contained_path
from daemon.store.journal import RunRow, TrendPoint, validate_run_id
from programs.compensation.common import UNIT_TEXT

_TEMPLATE = jinja2.Environment(autoescape=True).from_string("""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>rumba run {{ run.id }}</title>
<style>
body{font-family:system-ui,sans-serif;margin:2em;max-width:1200px;color:#222}
.badge{display:inline-block;padding:.3em .8em;border-radius:.3em;color:#fff;font-size:1.6em;
font-weight:bold;background:{{ colour }}}
.todo{font-size:1.15em;border-left:6px solid {{ colour }};padding:.4em .8em;background:#f6f7f9}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:.25em .6em;
text-align:right}th{background:#f3f3f3}td.l,th.l{text-align:left}
table.audit td,table.audit th{text-align:left}table.figures td,table.figures th{text-align:left}
table.sign td{height:2.2em;min-width:10em}
.PASS{color:#1b873f}.WARN{color:#c77700;font-weight:bold}.FAIL{color:#c62828;font-weight:bold}
.ERROR{color:#6a1b9a;font-weight:bold}
img{max-width:100%;border:1px solid #eee;margin:.5em 0}small{color:#666}
@media print{@page{size:A4;margin:12mm}body{margin:0;max-width:none;font-size:10pt}
.noprint{display:none}h2{break-after:avoid}img,table,.todo{break-inside:avoid}
.badge{-webkit-print-color-adjust:exact;print-color-adjust:exact}}
</style></head><body>
<h1>Machine {{ run.machine }} — run {{ run.id }}</h1>
<p><span class="badge">{{ verdict.status if verdict else run.state }}</span>
&nbsp; {{ run.summary }}</p>
{% if verdict %}<p class="todo"><b>What to do:</b> {{ todo }}</p>{% endif %}
<p class="noprint">For filing: <a href="{{ pdf_name }}">{{ pdf_name }}</a> (A4) — numbers:
<a href="{{ json_name }}">{{ json_name }}</a></p>
<table class="audit">{% for k, v in audit %}<tr><th>{{ k }}</th><td>{{ v }}</td></tr>
{% endfor %}</table>
<p><small>{{ analysis.touches }} touches; residual RMS {{ '%.2f' % analysis.residual_rms_um }} µm;
condition number {{ '%.3g' % analysis.condition_number }}{% if analysis.reference_run %}; drift
reference: run {{ analysis.reference_run }}{% endif %}</small></p>
<table class="figures">{% for f in figures %}<tr><th class="l">{{ f.label }}</th>
<td>{{ '%.1f %s' % (f.value, f.unit) if f.value is not none else '—' }}</td>
<td class="l"><small>{{ f.definition }}</small></td></tr>{% endfor %}</table>
{% if verdict and verdict.reasons %}<h2>Reasons</h2><ul>
{% for r in verdict.reasons %}<li>{{ r }}</li>{% endfor %}</ul>{% endif %}
{% if verdict %}<h2>Checks</h2><table><tr><th class="l">quantity</th><th>value</th><th>u</th>
<th class="l">unit</th><th class="l">limit</th><th class="l">status</th></tr>
{% for c in verdict.checks %}<tr><td class="l">{{ c.quantity }}</td>
<td>{{ '%+.2f' % c.value if c.value == c.value else '—' }}</td>
<td>{{ '%.2f' % c.std if c.std else '' }}</td><td class="l">{{ c.unit }}</td>
<td class="l">{{ c.limit }}</td><td class="l {{ c.status }}">{{ c.status }}</td></tr>
{% endfor %}</table>{% endif %}
<h2>Link errors</h2><p><small>{{ link_definition }}.</small></p><table><tr><th class="l">ISO
230-1 — name, controller term</th><th>value</th><th>u (k=1)</th><th class="l">unit</th></tr>
{% for n, v in analysis.links|dictsort %}<tr><td class="l">{{ audit_links.get(n, n) }}</td>
<td>{{ '%+.2f' % v.value }}</td><td>{{ '%.2f' % v.std }}</td>
<td class="l">{{ 'µrad' if v.unit == 'urad' else 'µm' }}</td></tr>{% endfor %}</table>
<p><small>Not observable: {{ analysis.unobservable|join(', ') or 'nothing' }}.</small></p>
{% if comp %}<h2>Compensation verified by this run</h2><p>Journal #{{ comp.row_id }}: written
after run {{ comp.source_run }}, confirmed by {{ comp.confirmed_by }} on {{ comp_time }}.</p>
{% if comp.writes %}<table class="writes"><tr><th class="l">address</th><th>written</th>
<th>was</th><th class="l">unit</th><th class="l">controller value</th></tr>
{% for w in comp.writes %}<tr><td class="l">{{ w.address }}</td><td>{{ w.written }}</td>
<td>{{ w.was }}</td><td class="l">{{ unit_text.get(w.unit, w.unit) }}</td>
<td class="l">{{ w.name }}</td></tr>{% endfor %}</table>{% else %}
<table><tr><th class="l">controller value</th><th class="l">address</th><th>old</th><th>new</th>
<th class="l">unit</th></tr>{% for v in comp.values %}<tr><td class="l">{{ v.name }}</td>
<td class="l">{{ v.address }}</td><td>{{ '%.6f' % v.old }}</td><td>{{ '%.6f' % v.new }}</td>
<td class="l">{{ v.unit }}</td></tr>{% endfor %}</table>{% endif %}
<table><tr><th class="l">ISO 230-1</th><th>before</th><th>u</th><th>after</th><th>u</th>
<th class="l">unit</th></tr>{% for l in comp.links %}<tr><td class="l">{{ l.name }}</td>
<td>{{ '%+.2f' % l.before }}</td><td>{{ '%.2f' % l.u_before }}</td>
<td>{{ '%+.2f' % l.after }}</td><td>{{ '%.2f' % l.u_after }}</td>
<td class="l">{{ 'µrad' if l.unit == 'urad' else 'µm' }}</td></tr>{% endfor %}</table>
{% if comp.distortion_before_um is not none and comp.distortion_after_um is not none %}<p>{{
figures[0].label }}: {{ '%.1f' % comp.distortion_before_um }} µm in run {{ comp.source_run }}
before, {{ '%.1f' % comp.distortion_after_um }} µm now.</p>{% endif %}{% endif %}
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
pose {{ analysis.stability.worst.pose }}{% if stability_span %}, over
{{ stability_span }}{% endif %}){% if analysis.thermal and analysis.thermal.status == "selected"
%}, after the fitted TCP drift was removed{% endif %}.</p>{% endif %}
{% if analysis.thermal %}<h2>Thermal drift during the run</h2>
{% if analysis.thermal.status == "selected" %}<p>A {{ analysis.thermal.shape }} drift of the
tool centre point was fitted with the link errors (BIC gain
{{ '%.1f' % analysis.thermal.bic_gain }}); the link errors above are estimated with it.</p>
<table><tr><th>axis</th><th>drift over the run µm</th><th>u µm</th></tr>
{% for a, d in analysis.thermal.over_run_um|dictsort %}<tr><td class="l">{{ a }}</td>
<td>{{ '%+.2f' % d.value }}</td><td>{{ '%.2f' % d.std }}</td></tr>{% endfor %}</table>
<p>Run {{ '%.1f' % analysis.thermal.span_min }} min{% if analysis.thermal.tau_min is not none
%}; time constant τ {{ '%.1f' % analysis.thermal.tau_min }} min{% if analysis.thermal.tau_std_min
is not none %} ± {{ '%.1f' % analysis.thermal.tau_std_min }}{% else %} (at its
{{ analysis.thermal.tau_bounded }} bound){% endif %}{% endif %}; link uncertainties grow at most
×{{ '%.2f' % analysis.thermal.link_inflation }} for it.</p>
{% else %}<p>{{ analysis.thermal.message }}</p>{% endif %}{% endif %}
<h2 id="index-scatter">{{ index_scatter.title }}</h2><p><small>{{ index_scatter.definition
}}.</small></p><ul class="index-scatter">{% for line in index_scatter.lines %}<li>{{ line }}</li>
{% endfor %}</ul>
{% if temperature_rows %}<h2>Temperatures during the run</h2>
<table><tr><th>channel</th><th>start °C</th><th>end °C</th><th>change °C</th><th>min … max °C</th>
<th>at each pose (pose: °C)</th><th>source</th></tr>
{% for t in temperature_rows %}<tr><td class="l">{{ t.name }}</td><td>{{ t.start }}</td>
<td>{{ t.end }}</td><td>{{ t.change }}</td><td>{{ t.range }}</td><td class="l">{{ t.per_pose }}
</td><td class="l">{{ t.source }}{% if t.unread %}<br>{{ t.unread }}{% endif %}</td></tr>
{% endfor %}</table>{% endif %}
{% if analysis.warnings %}<h2>Warnings</h2><ul>{% for w in analysis.warnings %}<li>{{ w }}</li>
{% endfor %}</ul>{% endif %}
{% if audit_doc.decision_rule %}<h2>Decision rule</h2><p>{{ audit_doc.decision_rule }}</p>
{% endif %}<h2>Approval</h2><table class="sign"><tr><th class="l">role</th><th class="l">name</th>
<th class="l">date</th><th class="l">signature</th></tr>{% for r in ("Prepared by", "Checked by",
"Approved by") %}<tr><td class="l">{{ r }}</td><td class="l">{{ prepared_by if loop.first else ''
}}</td><td class="l">{{ generated_date if loop.first else '' }}</td><td class="l"></td></tr>
{% endfor %}</table>
<p><small>rumba-cnc report generated {{ generated }}; numbers also in {{ json_name }}, for
filing {{ pdf_name }}.</small></p>
</body></html>
""")


def verdict_doc(judgement: Judgement | None) -> dict[str, Any] | None:
    """The verdict as the report shows it and writes it to its JSON (the journal's verdict
    record at report time: written back later, after the report)."""
    if judgement is None:
        return None
    return {"status": judgement.status, "reasons": list(judgement.reasons),
            "checks": [c.as_dict() for c in judgement.checks], "written_back": False}


__all__ = ["Audit", "audit_of", "build", "pdf_path", "render_plots", "write_report"]

PLOTS = {  # key: (title, draw, height in inches at the A4 text width)
    "distortion": ("Volumetric distortion (thesis Fig 3.10)", draw_distortion, 6.4),
    "cluster": ("Relocalisation vs local distortion", draw_cluster, 3.6),
    "links": ("Link errors", draw_links, 2.9),
    "trend": ("Trend over past runs", draw_trend, 6.0),
}


def render_plots(analysis: Analysis, centres: dict[tuple[int, str], Sequence[float]],
                 trend: list[TrendPoint], tol: Tolerances | None) -> dict[str, bytes | None]:
    """Every plot once, as PNG by ``PLOTS`` key (None when there is nothing to draw): the HTML
    embeds them, the PDF places them on its A4 pages."""
    args = {"distortion": (analysis, centres), "cluster": (analysis,),
            "links": (analysis, tol), "trend": (trend, tol)}
    return {k: png(draw, h, *args[k]) for k, (_, draw, h) in PLOTS.items()}


def build(run: RunRow, analysis: Analysis, judgement: Judgement | None,
          centre_rows: Iterable[Sequence[Any]], trend: list[TrendPoint],
          tol: Tolerances | None, audit: Audit | None = None,
          compensation: CompensationView | None = None) -> tuple[str, dict[str, Any]]:
    """(HTML text, JSON document) for one run: its record, analysis, judgement, centre rows
    (pose, ball, b, c, x, y, z, …), the trend of its machine (oldest first), the audit
    fields of its configuration and the compensation it verifies (before/after)."""
    html, doc, _ = _render(run, analysis, judgement, centre_rows, trend, tol, audit,
                           compensation)
    return html, doc


def _render(run: RunRow, analysis: Analysis, judgement: Judgement | None,
            centre_rows: Iterable[Sequence[Any]], trend: list[TrendPoint],
            tol: Tolerances | None, audit: Audit | None,
            compensation: CompensationView | None = None
            ) -> tuple[str, dict[str, Any], dict[str, bytes | None]]:
    audit = audit or Audit()
    verdict = verdict_doc(judgement)
    plots = render_plots(analysis, {(c[0], c[1]): c[4:7] for c in centre_rows}, trend, tol)
    health = analysis.health
    status = verdict["status"] if verdict else None
    figures = run_figures(analysis)  # one definition of each quantity
    index_scatter = index_scatter_doc(analysis)  # the one text of every screen
    doc = {
        "run": {k: getattr(run, k) for k in ("id", "machine", "trigger", "state", "reason",
                                               "plan", "artefact", "dialect", "touch_total",
                                               "started_at", "ended_at", "summary")},
        "verdict": verdict, "what_to_do": advice(status) if verdict else None,
        "audit": asdict(audit),
        "files": {"html": f"{run.id}.html", "json": f"{run.id}.json", "pdf": f"{run.id}.pdf"},
        "analysis": analysis.to_json(),
        "trend": [{"run_id": t.run_id, "started_at": t.started_at, "verdict": t.verdict,
                   "volumetric_max_um": volumetric_max_um(t.analysis),
                   "links": {k: v.value for k, v in t.analysis.links.items()}}
                  for t in trend],
        "compensation": compensation.to_json() if compensation else None,
        "figures": figures_json(figures), "links_definition": LINK_DEFINITION,
        "index_scatter": index_scatter,
    }
    stab = analysis.stability
    html = _TEMPLATE.render(
        run=run, verdict=verdict, analysis=analysis, todo=advice(status),
        plots=[(PLOTS[k][0], base64.b64encode(img).decode("ascii") if img else None)
               for k, img in plots.items()],
        audit=audit_rows(run, audit, analysis),
        temperature_rows=temperature_rows(analysis),
        colour=VERDICT_COLOURS.get(status or "ERROR", "#555"),
        generated=local_time(time.time()), json_name=f"{run.id}.json",
        pdf_name=f"{run.id}.pdf", comp=compensation, figures=figures, audit_doc=audit,
        index_scatter=index_scatter,
        audit_links=audit.link_names, link_definition=LINK_DEFINITION,
        prepared_by=prepared_by(run, audit), generated_date=time.strftime("%Y-%m-%d"),
        comp_time=local_time(compensation.applied_at) if compensation else "",
        unit_text=UNIT_TEXT,
        stability_span=duration_text(stab.span_min * 60)
        if stab is not None and stab.span_min is not None else "",
        health_rad=max((abs(h.radius_dev_um or 0.0) for h in health), default=0.0),
        health_form=max((h.form_rms_um or 0.0 for h in health), default=0.0))
    return html, doc, plots


def prepared_by(run: RunRow, audit: Audit) -> str:
    """Who prepared the measurement: the person who started the run, else the operator the
    configuration names, else blank (a name is written in by hand)."""
    return getattr(run, "started_by", "") or audit.operator or ""


def pdf_path(html_path: Path) -> Path:
    """The PDF written beside a report's HTML (same run id, same directory)."""
    return Path(html_path).with_suffix(".pdf")


def write_report(reports_dir: Path, run: RunRow, analysis: Analysis,
                 judgement: Judgement | None, centre_rows: Iterable[Sequence[Any]],
                 trend: list[TrendPoint], tol: Tolerances | None = None,
                 audit: Audit | None = None, compensation: CompensationView | None = None
                 ) -> tuple[Path, Path]:
    """Write ``<reports_dir>/<run id>.html``, ``.json`` and ``.pdf`` from what the caller holds
    (no journal access); returns the HTML and JSON paths (the PDF is ``pdf_path(html)``, and
    the JSON names it). The run id names the files: it is checked, and every path is proven to
    stay in ``reports_dir``."""
    run_id = validate_run_id(run.id)
    html, doc, plots = _render(run, analysis, judgement, centre_rows, trend, tol, audit,
                               compensation)
    reports_dir = Path(reports_dir)
    reports_dir.mkdir(parents=True, exist_ok=True)
    # after mkdir, so that the containment check sees the real directory and its symlinks
    html_path = contained_path(reports_dir, f"{run_id}.html")
    json_path = contained_path(reports_dir, f"{run_id}.json")
    pdf = contained_path(reports_dir, f"{run_id}.pdf")
    write_pdf(pdf, run, analysis, doc, audit or Audit(), plots,
              prepared_by(run, audit or Audit()))
    json_path.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    html_path.write_text(html, encoding="utf-8")
    return html_path, json_path
