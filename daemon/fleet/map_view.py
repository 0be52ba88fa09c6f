"""The fleet page's maps of the linear axes: a machine's map results (volumetric error max ± u
and RMS over the covered box, the verdict, covered strokes, what is not observable) as a table
of its page and as JSON (``/api/machines/NAME/maps``)."""

from __future__ import annotations

from collections.abc import Sequence
from html import escape
from typing import Any

from daemon.fleet.view import _badge, when
from daemon.store.map_results import MapResult


def _e(x: Any) -> str:
    return escape("" if x is None else str(x))


def covered_text(m: MapResult) -> str:
    """"X -400..400, Y -300..300, Z -100..400 mm"."""
    return ", ".join(f"{a} {lo:g}..{hi:g}" for a, (lo, hi) in
                     m.figures.get("covered_mm", {}).items()) + " mm"


def maps_section(maps: Sequence[MapResult]) -> str:
    """The machine page's section (empty without maps: the page stays as it was)."""
    if not maps:
        return ""
    rows = []
    for m in maps:
        u = "" if m.volumetric_max_u_um is None else f" ± {m.volumetric_max_u_um:.1f}"
        verdict = _badge(m.verdict) if m.verdict else "not judged (no limit)"
        gone = ", ".join(m.figures.get("unobservable", {})) or "—"
        rows.append(f'<tr class="map" data-map="{_e(m.id)}"><td>{_e(m.id)}</td>'
                    f"<td>{_e(when(m.created_at))}</td><td>{m.placements}</td>"
                    f"<td>{_e(covered_text(m))}</td>"
                    f'<td class="vmax">{m.volumetric_max_um:.1f}{u}</td>'
                    f'<td class="vrms">{m.volumetric_rms_um:.1f}</td><td>{verdict}</td>'
                    f"<td>{_e(m.limit_text)}</td><td>{_e(gone)}</td></tr>")
    return ('<h2>Maps of the linear axes</h2><table class="maps"><thead><tr><th>Map</th>'
            "<th>Recorded</th><th>Placements</th><th>Covered</th>"
            "<th>Volumetric max ± u µm</th><th>RMS µm</th><th>Verdict</th><th>Limit</th>"
            f"<th>Not observable</th></tr></thead><tbody>{''.join(rows)}</tbody></table>"
            '<p class="definition">Map volumetric error: the tool tip\'s actual minus nominal '
            "position relative to the workpiece over the covered box, rotary axes at zero, "
            "after its best rigid-body motion; u its standard uncertainty.</p>")


def maps_json(maps: Sequence[MapResult]) -> list[dict[str, Any]]:
    """The API's rows (no file paths: they are the daemon's, not the fleet page's)."""
    out = []
    for m in maps:
        d = m.as_dict()
        for k in ("json_path", "report_html", "report_pdf"):
            d.pop(k)
        out.append(d)
    return out
