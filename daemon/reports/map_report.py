"""The map report of ``rumba map --report DIR``: ``map.html`` (self-contained, plots embedded as
base64 PNG, a print layout), ``map.json`` (the map itself, contracts/linear_map.py: the same
numbers) and ``map.pdf`` (four A4 pages, ``map_pdf``) for filing, all from one map document and
its model as the run report does (``report``): plots drawn once (``map_plots``), words from
``map_text``."""

from __future__ import annotations

import base64
import json
import time
from pathlib import Path
from typing import Any

import jinja2
import numpy as np

from contracts.linear_map import LinearMapFile
from daemon.reports.audit import local_time
from daemon.reports.map_pdf import write_map_pdf
from daemon.reports.map_plots import draw_functions, draw_slices, draw_volume, slices
from daemon.reports.map_text import (
    box_text,
    degrees_text,
    figure_rows,
    states,
    title,
    unit_text,
    unobservable_lines,
)
from daemon.reports.plots import VERDICT_COLOURS, png
from daemon.safepath import contained_path
from identification.linmap.field import MapModel, predict_field

SLICE_N = 9  # arrows per side of each slice
NAMES = {"html": "map.html", "json": "map.json", "pdf": "map.pdf"}
PLOTS = {  # key: (title, height in inches at the A4 text width)
    "volume": ("Covered volume", 3.6),
    "functions": ("Motion errors with their ±2u bands", 9.6),
    "slices": ("Volumetric error on three slices", 6.0),
}

_TEMPLATE = jinja2.Environment(autoescape=True).from_string("""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>rumba map {{ d.machine.name }}</title>
<style>
body{font-family:system-ui,sans-serif;margin:2em;max-width:1200px;color:#222}
.badge{display:inline-block;padding:.3em .8em;border-radius:.3em;color:#fff;font-size:1.6em;
font-weight:bold;background:{{ colour }}}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:.25em .6em;
text-align:right}th{background:#f3f3f3}td.l,th.l{text-align:left}
.PASS{color:#1b873f}.WARN{color:#c77700;font-weight:bold}.FAIL{color:#c62828;font-weight:bold}
tr.none td{color:#777;background:#f6f6f6}.nobs{font-weight:bold;color:#555}
table.functions td:first-child,table.functions td:nth-child(2){white-space:nowrap}
img{max-width:100%;border:1px solid #eee;margin:.5em 0}small{color:#666}
@media print{@page{size:A4;margin:12mm}body{margin:0;max-width:none;font-size:10pt}
.noprint{display:none}h2{break-after:avoid}img,table{break-inside:avoid}
.badge{-webkit-print-color-adjust:exact;print-color-adjust:exact}}
</style></head><body>
<h1>Map of the linear axes — machine {{ d.machine.name }} ({{ d.machine.topology }})</h1>
<p><span class="badge">{{ status or "NOT JUDGED" }}</span> &nbsp; map of {{ d.created_utc }},
{{ d.placements|length }} placement(s); covered box {{ box }}.</p>
<p class="noprint">For filing: <a href="{{ names.pdf }}">{{ names.pdf }}</a> (A4) — numbers:
<a href="{{ names.json }}">{{ names.json }}</a> ({{ d.schema_ }})</p>
<h2>Figures</h2><table class="map-figures"><tr><th class="l">figure</th><th>value</th>
<th class="l">status</th><th class="l">where, limit</th></tr>{% for f in figures %}<tr>
<th class="l">{{ f.label }}</th><td class="value">{{ f.value }}</td>
<td class="l {{ f.status }}">{{ f.status or "—" }}</td><td class="l"><small>{{ f.detail }}</small>
</td></tr>{% endfor %}</table>
<p><small>Volumetric error: the tool tip's actual minus nominal position relative to the
workpiece at commanded X, Y, Z with the rotary axes at zero, in the workpiece frame; rigid
convention: {{ d.rigid_convention }}.</small></p>
<h2>Placements</h2><table><tr><th class="l">placement</th><th class="l">log</th>
<th class="l">artefact</th><th>centres</th><th>poses</th><th>residual RMS µm</th></tr>
{% for p in d.placements %}<tr><td class="l">{{ loop.index }} ({{ p.name }})</td>
<td class="l">{{ p.log }}</td><td class="l">{{ p.artefact }}</td><td>{{ p.centres }}</td>
<td>{{ p.poses }}</td><td>{{ '%.3f' % p.residual_rms_um }}</td></tr>{% endfor %}</table>
<p>Fit: residual RMS {{ '%.3f' % d.fit.residual_rms_um }} µm, {{ d.fit.iterations }}
iteration(s), {{ 'converged' if d.fit.converged else 'NOT converged' }}{% if d.order %};
degrees {{ degrees }} chosen by {{ d.order.method }}{% endif %}.</p>
{% if d.holdout %}<p>Held-out placement ({{ d.holdout.log }}, {{ d.holdout.centres }} centres):
RMS {{ '%.2f' % d.holdout.rms_before_um }} → {{ '%.2f' % d.holdout.rms_after_um }} µm, max
{{ '%.2f' % d.holdout.max_before_um }} → {{ '%.2f' % d.holdout.max_after_um }} µm without → with
the map.</p>{% endif %}
{% for key, head, img in plots if key == "volume" and img %}<h2>{{ head }}</h2>
<img alt="{{ head }}" src="data:image/png;base64,{{ img }}">{% endfor %}
<h2>Motion errors (ISO 230-1)</h2>
<table class="functions"><tr><th class="l">ISO 230-1</th><th class="l">state</th>
<th>max |e| over the range</th><th>u there (k=1)</th><th class="l">unit</th><th>terms</th>
<th class="l">what holds the rest</th></tr>{% for f in d.functions %}{% set s = st[f.name] %}
<tr class="{{ s.state }}" id="{{ f.name }}"><td class="l">{{ name(f) }}</td>
<td class="l">{% if s.state == "none" %}<span class="nobs">not observable</span>{% elif
s.state == "partly" %}observable in part{% else %}observable{% endif %}</td>
<td>{{ '%.2f' % s.max_abs if s.max_abs is not none else '—' }}</td>
<td>{{ '%.2f' % s.u_at_max if s.u_at_max is not none else '—' }}</td>
<td class="l">{{ s.unit }}</td><td>{{ f.terms|length }}</td>
<td class="l"><small>{{ s.why }}</small></td></tr>{% endfor %}</table>
{% for key, head, img in plots if key != "volume" and img %}<h2>{{ head }}</h2>
<img alt="{{ head }}" src="data:image/png;base64,{{ img }}">{% endfor %}
<h2 id="not-observable">Not observable</h2><ul class="unobservable">
{% for line in unobservable %}<li>{{ line }}</li>{% endfor %}</ul>
<p><small>{{ d.observability.note }}</small></p>
<h2>Link errors estimated with the map</h2><table><tr><th class="l">ISO 230-1</th>
<th>value</th><th>u (k=1)</th><th class="l">unit</th></tr>{% for n, v in d.links.items() %}
<tr><td class="l">{{ n }}</td><td>{{ '%+.2f' % v.value }}</td><td>{{ '%.2f' % v.std }}</td>
<td class="l">{{ unit(v.unit) }}</td></tr>{% endfor %}</table>
<p><small>Basis: {{ d.basis.argument }}.</small></p>
{% if d.warnings %}<h2>Warnings</h2><ul>{% for w in d.warnings %}<li>{{ w }}</li>{% endfor %}
</ul>{% endif %}
<p><small>rumba-cnc map report generated {{ generated }}; numbers also in {{ names.json }},
for filing {{ names.pdf }}.</small></p>
</body></html>
""")


def slice_fields(doc: LinearMapFile, model: MapModel, n: int = SLICE_N) -> list:
    """The three slices of the report with the map's own prediction (rigid convention)."""
    def predict(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = predict_field(model, pts, check=False)
        return p.error_um, p.u_um

    return slices(doc, n, predict)


def render_plots(doc: LinearMapFile, model: MapModel) -> dict[str, bytes | None]:
    """Every plot once, as PNG by ``PLOTS`` key (the HTML embeds them, the PDF places them)."""
    return {"volume": png(draw_volume, PLOTS["volume"][1], doc),
            "functions": png(draw_functions, PLOTS["functions"][1], doc),
            "slices": png(draw_slices, PLOTS["slices"][1], slice_fields(doc, model))}


def render_html(doc: LinearMapFile, plots: dict[str, bytes | None]) -> str:
    status = doc.figures.volumetric_max_um.status
    return _TEMPLATE.render(
        d=doc, status=status, colour=VERDICT_COLOURS.get(status or "", "#555555"),
        box=box_text(doc), names=NAMES, degrees=degrees_text(doc), figures=figure_rows(doc),
        st=states(doc),
        name=title, unit=unit_text, unobservable=unobservable_lines(doc),
        plots=[(k, PLOTS[k][0], base64.b64encode(v).decode("ascii") if v else None)
               for k, v in plots.items()],
        generated=local_time(time.time()))


def check_report_dir(report_dir: Path | str) -> Path:
    """``report_dir`` created if missing and proven writable, before the fit runs; ``OSError``
    (with the reason) when it cannot be."""
    d = Path(report_dir)
    d.mkdir(parents=True, exist_ok=True)
    probe = contained_path(d, ".rumba-map-report-probe")
    probe.write_bytes(b"")
    probe.unlink()
    return d


def write_map_report(report_dir: Path | str, doc: LinearMapFile, model: MapModel
                     ) -> dict[str, Path]:
    """Write ``map.html``, ``map.json`` and ``map.pdf`` into ``report_dir``; their paths by
    kind. ``OSError`` when a file cannot be written."""
    d = check_report_dir(report_dir)
    paths = {k: contained_path(d, n) for k, n in NAMES.items()}
    plots = render_plots(doc, model)
    data: dict[str, Any] = doc.to_json()
    paths["json"].write_text(json.dumps(data, indent=1, ensure_ascii=False) + "\n",
                             encoding="utf-8")
    write_map_pdf(paths["pdf"], doc, plots)
    paths["html"].write_text(render_html(doc, plots), encoding="utf-8")
    return paths
