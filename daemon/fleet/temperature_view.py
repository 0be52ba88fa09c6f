"""The fleet page's link-against-temperature view as text (no I/O): a chosen
link error of a machine's runs against a chosen channel's mean over each run, from the raw
readings in the fleet store, with the statistics of ``rumba history --against-temperature``
(daemon/analysis/temperature_trend.py ``fit``: r, slope ± u, the 95 % Student's t interval) and
an inline SVG scatter with each run's u and the fitted line."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from daemon.analysis.temperature_trend import TempFit, TempPoint
from daemon.fleet.chart import LEFT_PX, RIGHT_PX, WIDTH_PX, Frame, padded, ticks
from daemon.fleet.view import _e, _page, finite, when

_H, _T, _B = 320, 12, 40  # the scatter's height, top and bottom margins, px


def scatter(pts: Sequence[TempPoint], f: TempFit, link: str, channel: str, unit: str) -> str:
    """Each run a point (°C, value) with its ±u bar, the OLS line through the means."""
    if not pts:
        return '<p class="empty">No run has both this link and this channel.</p>'
    xs = [p.temperature_c for p in pts]
    x0, x1 = padded(min(xs), max(xs))
    ys = [v for p in pts for v in (p.value - (p.std or 0.0), p.value + (p.std or 0.0))]
    frame = Frame(_H, _T, _B, *padded(min(ys), max(ys)))
    y = frame.y

    def x(t: float) -> float:
        return LEFT_PX + (WIDTH_PX - LEFT_PX - RIGHT_PX) * (t - x0) / (x1 - x0)

    out = [frame.open({"class": "scatter", "data-link": link, "data-channel": channel},
                      f"{link} in {unit} against {channel} in °C"), *frame.y_grid()]
    for tx in ticks(x0, x1):
        out.append(f'<text class="tick" x="{x(tx):.1f}" y="{_H - _B + 14}" '
                   f'text-anchor="middle">{tx:g}</text>')
    out.append(frame.y_label(f"{link} ({unit})") +
               f'<text class="axis-label x" x="{(LEFT_PX + WIDTH_PX - RIGHT_PX) / 2:.0f}" '
               f'y="{_H - 6}" text-anchor="middle">{_e(channel)}, mean over the run (°C)</text>')
    if f.slope is not None:
        mt, mv = sum(xs) / len(xs), sum(p.value for p in pts) / len(pts)
        lo, hi = min(xs), max(xs)
        out.append(f'<line class="fit" x1="{x(lo):.1f}" x2="{x(hi):.1f}" '
                   f'y1="{y(mv + f.slope * (lo - mt)):.1f}" '
                   f'y2="{y(mv + f.slope * (hi - mt)):.1f}"/>')
    for p in pts:
        if p.std:
            out.append(f'<line class="ubar" x1="{x(p.temperature_c):.1f}" '
                       f'x2="{x(p.temperature_c):.1f}" y1="{y(p.value - p.std):.1f}" '
                       f'y2="{y(p.value + p.std):.1f}"/>')
        u = f" ± {p.std:.2f}" if p.std is not None else ""
        out.append(f'<circle class="pt" data-run="{_e(p.run_id)}" cx="{x(p.temperature_c):.1f}" '
                   f'cy="{y(p.value):.1f}" r="3.5"><title>{_e(p.run_id)}: '
                   f"{p.temperature_c:.2f} °C, {p.value:+.2f}{_e(u)} {_e(unit)}</title></circle>")
    out.append("</svg>")
    return "".join(out)


def _options(names: Sequence[str], chosen: str) -> str:
    return "".join(f'<option value="{_e(n)}"{" selected" if n == chosen else ""}>{_e(n)}'
                   "</option>" for n in names)


def _figures(f: TempFit) -> str:
    """The fit's numbers, each in an element of its own (scripts and tests read them)."""
    if f.slope is None or f.r is None:
        return f'<p class="fit-none" data-n="{f.n}">{f.n} runs with both: at least 3 ' \
               "runs at two or more temperatures needed for a slope.</p>"
    u = "—" if f.slope_std is None else f"{f.slope_std:.3g}"
    u95 = "—" if f.slope_u95 is None else f"{f.slope_u95:.3g}"
    lo_hi = ("" if f.slope_u95 is None else
             f" ({f.slope - f.slope_u95:+.3g} … {f.slope + f.slope_u95:+.3g})")
    return ('<dl class="fit">'
            f'<dt>runs</dt><dd class="n">{f.n}</dd>'
            f'<dt>r (Pearson)</dt><dd class="r">{f.r:+.2f}</dd>'
            f'<dt>slope ± u</dt><dd class="slope">{f.slope:+.3g} ± {u} {_e(f.unit)}</dd>'
            f"<dt>95 % interval (Student's t, {f.n - 2} dof)</dt>"
            f'<dd class="u95">± {u95} {_e(f.unit)}{lo_hi}</dd></dl>')


def page(name: str, channel: str, link: str, channels: Sequence[str], links: Sequence[str],
         rows: Sequence[dict[str, Any]], pts: Sequence[TempPoint], f: TempFit, unit: str,
         days: int) -> str:
    """The whole view: the choice of channel and link, the fit, the scatter, the runs."""
    form = (f'<form class="against" method="get" action="/machines/{_e(name)}/temperature">'
            f'<label>Link <select name="link" id="link">{_options(links, link)}</select></label> '
            f'<label>Channel <select name="channel" id="channel">'
            f"{_options(channels, channel)}</select></label> "
            f'<label>Days <input name="days" id="days" type="number" min="1" value="{days}">'
            '</label> <button type="submit">Show</button></form>')
    used = {p.run_id: p for p in pts}
    body_rows = "".join(
        f'<tr data-run="{_e(r["run_id"])}"><td>{_e(r["run_id"])}</td>'
        f'<td>{_e(when(r["started_at"]))}</td>'
        f'<td>{int(r.get("read") or 0)} of {int(r.get("readings") or 0)}</td>'
        + (f'<td class="t">{used[r["run_id"]].temperature_c:.2f}</td>'
           f'<td class="v">{used[r["run_id"]].value:+.2f}</td>'
           if r["run_id"] in used else '<td colspan="2">not in the fit (no value)</td>')
        + "</tr>" for r in rows)
    text = f.text(link, channel)
    html = (f'<header><p><a href="/machines/{_e(name)}">← {_e(name)}</a></p>'
            f"<h1>{_e(name)}: link error against temperature</h1>"
            f'<p class="sub">last {days} days; each run one point: the channel\'s mean over '
            "the run's raw readings (every pose, else start and end) and the link's "
            "identified value ± u</p></header><main>"
            f'{form}<p class="fit-text">{_e(text)}</p>{_figures(f)}'
            f"{scatter(pts, f, link, channel, unit)}"
            '<table class="runs against"><thead><tr><th>Run</th><th>Started</th>'
            f"<th>{_e(channel)} readings</th><th>°C (mean)</th><th>{_e(link)} ({_e(unit)})</th>"
            f"</tr></thead><tbody>{body_rows}</tbody></table></main>")
    return _page(f"rumba fleet — {name} — {link} against {channel}", html)


def links_of(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The link names the runs carry, sorted (the store's jsonb keeps no analysis order)."""
    out: list[str] = []
    for r in rows:
        links = r.get("links")
        for n, v in (links.items() if isinstance(links, dict) else ()):
            if n not in out and isinstance(v, dict) and finite(v.get("value")) is not None:
                out.append(n)
    return sorted(out)
