"""HTML report of a gap diagnosis: where the gap lies, ranked candidates, before/after plots."""

from __future__ import annotations

import base64
import io

import jinja2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from identification.gap.locate import shown_locations
from identification.gap.structure_shape import bump

_TEMPLATE = jinja2.Environment(autoescape=True).from_string("""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{{ title }}</title>
<style>
body{font-family:system-ui,sans-serif;margin:2em;max-width:70em;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:.3em .6em}
th{background:#f3f3f3}td.n{text-align:right;font-variant-numeric:tabular-nums}
.verdict{font-size:1.2em;padding:.8em;border-radius:.4em;background:#eef}
.sig{color:#a00;font-weight:600}img{max-width:100%}
</style></head><body>
<h1>{{ title }}</h1>
<p class="verdict"><b>Verdict: {{ v.effect }}{% if v.axis %} ({{ v.axis }}){% endif %}</b>
—
{{ v.message }}.<br>Held-out RMS {{ "%.3f"|format(v.holdout_rms_before_um) }} µm →
{{ "%.3f"|format(v.holdout_rms_after_um) }} µm; noise floor
{{ "%.3f"|format(r.noise_floor_um) }} µm
(per coordinate), held-out floor {{ "%.3f"|format(r.noise.holdout_floor_um) }} µm.</p>
{% set touches = r.noise.source.startswith("sphere-fit") %}
<p>Noise: {{ r.noise.source }}{% if touches %}; trigger repeatability
{{ "%.3f"|format(r.noise.sigma_touch_um) }} µm{% endif %}.
{% if r.dropped_groups %}{{ r.dropped_groups }} incomplete ball-pose(s) left out.{% endif %}</p>
{% set fp = r.noise.parts %}{% if fp %}<h2>What the floor is made of</h2>
<table><tr><th>part</th><th>µm (RMS per observation)</th><th>share of the floor²</th></tr>
{% for key, name in [("trigger_um", "trigger noise of the touches"),
                     ("index_um", "visit scatter: rigid index error of the rotary axes"),
                     ("ball_visit_um", "visit scatter: centre scatter per ball visit")] %}
<tr><td>{{ name }}</td><td class="n">{{ "%.3f"|format(fp[key]) }}</td>
<td class="n">{{ "%.0f"|format(100 * fp[key] ** 2 / [r.noise_floor_um ** 2, 1e-30]|max) }} %</td>
</tr>{% endfor %}</table>
<p>{{ fp.message }}.</p>{% endif %}
{% if r.scatter %}<p>Per-visit scatter: {{ r.scatter.message }}.</p>{% endif %}
{% set st = r.structure %}{% if st %}<h2>Structure along the linear axes</h2>
<p{% if st.found %} class="sig"{% endif %}>{{ st.message }}.</p>
<table><tr><th>axis</th><th>adjusted p</th><th>largest z</th></tr>
{% for a, x in st.axes.items() %}<tr><td>{{ a }}</td><td class="n">{{ x.p_value }}</td>
<td class="n">{{ x.z }}</td></tr>{% endfor %}</table>
{% if st.located %}<p>Located along {{ st.located.axis }}: {{ st.located.shape }} shape,
{% if st.located.shape == "cyclic" %}period {{ st.located.period_mm }} mm{% else %}centred at
{{ st.located.centre_mm }} mm over {{ st.located.width_mm }} mm{% endif %},
{{ st.located.size_um }} µm in {% if st.located.channel == "form" %}the sphere form
residual{% else %}centre {{ st.located.channel }}{% endif %} (the ball centres reach
{{ st.located.span_mm[0] }}…{{ st.located.span_mm[1] }} mm).
{% if st.explained_by_selected %}The selected effects remove it.{% endif %}</p>{% endif %}
{% if along %}<img alt="residuals along the axis" src="data:image/png;base64,{{ along }}">
{% endif %}
<p>Test: {{ st.test }}; {{ st.draws }} Monte Carlo draws under the run's visit model,
family-wise α = {{ st.alpha }} over the axes, channels, lags and shapes. Decision rule: structure
found, the centre scatter per ball visit is not credited to the floor (trigger noise and rigid
index scatter only); none, it is.</p>{% endif %}
{% if r.ball_step %}<p><b>Ball moved:</b> {{ r.ball_step.message }}.</p>{% endif %}
{% for a in r.absorbed %}<p>Absorbed: {{ a.effect }} — {{ a.what }}
({{ "%.2f"|format(a.value_um) }} ± {{ "%.2f"|format(a.std_um) }} µm).</p>{% endfor %}
<p>Judged on: {{ r.split }}. Twin: {{ r.twin.n_params }} parameters (setup + links
{{ r.twin.links|join(", ") }}). Observations per ball-pose: centre x, y, z{% if touches %} and the
sphere-fit form residual{% endif %} (µm).</p>
{% if r.time_check %}<p>Drift checked on {{ r.time_check.split }}: explains
{{ "%.0f"|format(100 * r.time_check.explained_fraction) }} % of the held-out excess there
(leaving poses out: {{ "%.0f"|format(100 * r.time_check.explained_fraction_pose) }} %) —
{% if r.time_check.confirmed %}confirmed{% else %}not confirmed: its time course does not
extrapolate{% endif %}.
</p>{% endif %}
{% if r.known %}<h2>Effects the twin already models</h2>
<table><tr><th>effect</th><th>axis</th><th>how</th><th>parameters</th></tr>
{% for k in r.known %}<tr><td>{{ k.effect }}</td><td>{{ k.axis or "" }}</td>
<td>{{ "fitted with the setup and links on the training data" if k.fitted else "given" }}</td>
<td>{% for n, p in k.params.items() %}{{ n }} = {{ "%.3g"|format(p.value) }}
{%- if p.std is not none %} ± {{ "%.2g"|format(p.std) }}{% endif %} {{ p.unit }}<br>
{%- endfor %}</td></tr>{% endfor %}
</table><p>The gap below is what remains once these effects are in the twin.</p>{% endif %}
{% if r.outliers %}<h2>Measurement outliers (left out)</h2>
<table><tr><th>log</th><th>pose</th><th>b°</th><th>c°</th><th>ball</th><th>repeat</th>
<th>touch</th><th>size µm</th><th>robust z</th><th>stage</th></tr>
{% for o in r.outliers %}<tr><td>{{ o.log }}</td><td class="n">{{ o.pose }}</td>
<td class="n">{{ o.b_deg }}</td><td class="n">{{ o.c_deg }}</td><td>{{ o.ball }}</td>
<td class="n">{{ o.repeat }}</td><td class="n">{{ o.touch }}</td>
<td class="n">{{ "%+.1f"|format(o.size_um) }}</td><td class="n">{{ "%.0f"|format(o.score) }}</td>
<td>{{ o.stage }}</td></tr>{% endfor %}</table>
<p>One touch of each visit lies off the sphere the rest of the run predicts (a chip, dirt,
coolant, a bad trigger): {{ r.outlier_test.visits }} visits screened against the run's median
and MAD (sphere radius and form, centre against the twin and the pose's other balls); the
diagnosis below is that of the other visits.</p>{% endif %}
<h2>Where the gap lies</h2>
{% if shown %}<table><tr><th>by</th><th>where</th><th>RMS µm</th><th>× floor</th>
<th>p</th></tr>{% for l in shown %}<tr><td>{{ l.by }}</td><td>{{ l.key }}</td>
<td class="n">{{ "%.3f"|format(l.rms_um) }}</td>
<td class="n">{{ "%.2f"|format(l.ratio_to_floor) }}</td>
<td class="n">{{ l.p_value }}{% if not l.significant %} (not significant alone){% endif %}
</td></tr>{% endfor %}</table>
{% if more or below %}<p>… {% if more %}{{ more }} more above the floor{% endif %}
{% if more and below %} and {% endif %}{% if below %}{{ below }} below it{% endif %}
(every cell in the JSON and in the plots below).</p>{% endif %}
{% else %}<p>No breakdown stands significantly above the floor.</p>{% endif %}
{% for name, img in where %}<h3>By {{ name }}</h3>
<img alt="gap by {{ name }}" src="data:image/png;base64,{{ img }}">{% endfor %}
<h2>Candidates (best first)</h2>
<img alt="ranked candidates" src="data:image/png;base64,{{ ranked }}">
<table><tr><th>effect</th><th>axis</th><th>held-out RMS µm</th><th>explained</th>
<th>significant</th><th>p</th><th>ΔBIC</th><th>visible dof</th><th>parameters</th>
<th>cannot be told from</th></tr>
{% for c in r.candidates %}<tr><td>{{ c.effect }}</td><td>{{ c.axis or "" }}</td>
<td class="n">{{ "%.3f"|format(c.holdout_rms_um) }}</td>
<td class="n">{{ "%.0f"|format(100 * c.explained_fraction) }} %</td>
<td class="{{ 'sig' if c.significant else '' }}">{{ "yes" if c.significant else "no" }}</td>
<td class="n">{{ c.p_value }}</td><td class="n">{{ c.delta_bic }}</td>
<td class="n">{{ c.visible_dof }}/{{ c.n_params }}</td>
<td>{% for k, p in c.params.items() %}{{ k }} = {{ "%.3g"|format(p.value) }}
{%- if p.std is not none %} ± {{ "%.2g"|format(p.std) }}{% endif %} {{ p.unit }}<br>
{%- endfor %}</td>
<td>{{ c.indistinguishable_from|join(", ") }}</td></tr>{% endfor %}</table>
{% if r.invisible %}<h3>Not visible on this probing pattern</h3><ul>
{% for i in r.invisible %}<li>{{ i.effect }}{% if i.axis %} {{ i.axis }}{% endif %}:
{{ i.reason }}</li>{% endfor %}</ul>{% endif %}
<h2>Before / after</h2>
<img alt="held-out residuals before and after" src="data:image/png;base64,{{ before_after }}">
</body></html>
""")


def _png(fig: plt.Figure) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _where_plots(rep: dict) -> list[tuple[str, str]]:
    kinds = [k for k in dict.fromkeys(c["by"] for c in rep["location"])]
    out = []
    floor = rep["noise"]["holdout_floor_um"]
    for kind in kinds:
        cells = [c for c in rep["breakdowns"] if c["by"] == kind]
        fig, ax = plt.subplots(figsize=(max(5.0, 0.45 * len(cells)), 3.0))
        colors = ["#c0392b" if c["significant"] else "#7f8c8d" for c in cells]
        ax.bar(range(len(cells)), [c["rms_um"] for c in cells], color=colors)
        ax.axhline(floor, color="k", ls="--", lw=1, label="held-out floor")
        ax.set_xticks(range(len(cells)), [c["key"] for c in cells], rotation=60, ha="right",
                      fontsize=7)
        ax.set_ylabel("held-out RMS (µm)")
        ax.legend(fontsize=7)
        out.append((kind, _png(fig)))
    return out


def _ranked_plot(rep: dict) -> str:
    cands = rep["candidates"][:15]
    fig, ax = plt.subplots(figsize=(6.5, 0.3 * len(cands) + 1.2))
    labels = [c["effect"] + (f":{c['axis']}" if c["axis"] else "") for c in cands]
    colors = ["#27ae60" if c["significant"] else "#95a5a6" for c in cands]
    ax.barh(range(len(cands)), [c["holdout_rms_um"] for c in cands], color=colors)
    ax.axvline(rep["baseline"]["holdout_rms_um"], color="#c0392b", lw=1, label="twin alone")
    ax.axvline(rep["noise"]["holdout_floor_um"], color="k", ls="--", lw=1, label="floor")
    ax.set_yticks(range(len(cands)), labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("held-out RMS with the candidate (µm)")
    ax.legend(fontsize=7)
    return _png(fig)


def _before_after(rep: dict) -> str:
    s = rep["residuals"]
    before = np.linalg.norm(np.asarray(s["before_um"])[:, :3], axis=1)
    after = np.linalg.norm(np.asarray(s["after_um"])[:, :3], axis=1)
    t = np.asarray(s["t_s"]) / 60.0
    fig, ax = plt.subplots(figsize=(7.0, 3.0))
    ax.plot(t, before, "o", ms=3, color="#c0392b", label="twin alone")
    ax.plot(t, after, "o", ms=3, color="#27ae60", label="with selected effects")
    ax.set_xlabel("time (min)")
    ax.set_ylabel("|held-out centre residual| (µm)")
    ax.legend(fontsize=7)
    return _png(fig)


def _along_plot(rep: dict) -> str | None:
    """Held-out centre residuals against the position along the located axis."""
    loc = (rep.get("structure") or {}).get("located")
    s = rep["residuals"]
    if not loc or "xyz_mm" not in s:
        return None
    q = np.asarray(s["xyz_mm"], float)[:, "XYZ".index(loc["axis"])]
    e = np.asarray(s["before_um"], float)
    fig, ax = plt.subplots(figsize=(7.0, 3.0))
    for k, (name, color) in enumerate(zip("xyz", ("#c0392b", "#27ae60", "#2980b9"),
                                          strict=True)):
        ax.plot(q, e[:, k], "o", ms=3, color=color, label=f"centre {name}")
    ax.axhline(0.0, color="k", lw=0.5)
    coef = (loc.get("coefficients_um") or {}).get(loc["channel"])
    if coef is not None and loc["channel"] != "form":
        grid = np.linspace(*loc["span_mm"], 600)
        w = 2 * np.pi * grid / loc.get("period_mm", 1.0)
        y = (coef[0] * np.cos(w) + coef[1] * np.sin(w)) if loc["shape"] == "cyclic" else \
            coef[0] * bump(grid, loc["centre_mm"], loc["width_mm"])
        k = "xyz".index(loc["channel"])
        ax.plot(grid, y, "-", color=("#c0392b", "#27ae60", "#2980b9")[k], lw=1.2,
                label=f"located {loc['shape']} shape, centre {loc['channel']}")
    ax.set_xlabel(f"{loc['axis']} of the ball centre (mm)")
    ax.set_ylabel("held-out residual of the twin (µm)")
    ax.legend(fontsize=7)
    return _png(fig)


def render(rep: dict, title: str = "Gap diagnosis") -> str:
    """The whole report as one self-contained HTML page (plots embedded as PNG)."""
    shown, more, below = shown_locations(rep["location"], rep["breakdowns"])
    return _TEMPLATE.render(title=title, r=rep, v=rep["verdict"], where=_where_plots(rep),
                            shown=shown, more=more, below=below,
                            ranked=_ranked_plot(rep), before_after=_before_after(rep),
                            along=_along_plot(rep))
