"""The map report for filing: a PDF of four A4 pages, laid out as the run report's PDF (``pdf``:
its page writer, image placement and font settings).

Page 1: verdict, the figures, placements, fit, held-out check, covered volume. Page 2: the 18
motion errors with their 2u bands. Page 3: the error field on three slices and each function's
state and size. Page 4: what is not observable in words, the link errors, the warnings. Lines
that do not fit on page 4 are counted, not drawn (the HTML and JSON hold all of them).
"""

from __future__ import annotations

import datetime
from pathlib import Path

import matplotlib
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure
from matplotlib.patches import FancyBboxPatch

from contracts.linear_map import LinearMapFile
from daemon.reports.audit import local_time
from daemon.reports.map_text import (
    box_text,
    degrees_text,
    figure_rows,
    states,
    title,
    unobservable_lines,
)
from daemon.reports.pdf import (
    A4_IN,
    FOOTER_IN,
    MARGIN_IN,
    ONE_SUBSET,
    STATUS_COLOURS,
    _Page,
    _save,
    _stack,
)

PAGES = 4
WIDTH = 128  # characters of a wrapped 8 pt line at the text width


def _footer(fig: Figure, doc: LinearMapFile, page: int, generated: str) -> None:
    fig.text(0.5, 0.012, f"rumba-cnc — map of the linear axes — machine {doc.machine.get('name')}"
                         f" — map of {doc.created_utc} — generated {generated} — page {page} of "
                         f"{PAGES}", ha="center", fontsize=6.5, color="#666666", parse_math=False)


def _head(p: _Page, text: str) -> None:
    p.y += 0.06
    p.line(text, size=10, weight="bold", gap=1.25)


def _page1(fig: Figure, doc: LinearMapFile) -> float:
    p = _Page(fig)
    status = doc.figures.volumetric_max_um.status or "NOT JUDGED"
    p.line("rumba-cnc — volumetric map of the linear axes (ISO 230-1 motion errors) from the "
           "touch probe and the ball artefact", color="#555555")
    p.line(f"Machine {doc.machine.get('name')} ({doc.machine.get('topology')}) — map of "
           f"{doc.created_utc}", size=14, gap=1.25, weight="bold")
    colour = STATUS_COLOURS.get(status, "#555555")
    x0, y0 = p._xy(MARGIN_IN, p.y + 0.42)
    fig.add_artist(FancyBboxPatch((x0, y0), 1.6 / A4_IN[0], 0.38 / A4_IN[1],
                                  boxstyle="round,pad=0.002", transform=fig.transFigure,
                                  facecolor=colour, edgecolor="none"))
    fig.text(*p._xy(MARGIN_IN + 0.8, p.y + 0.23), status, fontsize=15, weight="bold",
             color="white", ha="center", va="center", parse_math=False)
    p.text(MARGIN_IN + 1.8, f"{len(doc.placements)} placement(s); covered box "
                            f"{box_text(doc)}", size=8.5, dy=0.14)
    p.y += 0.55
    p.rule()
    _head(p, "Figures")
    for r in figure_rows(doc):
        p.text(MARGIN_IN, r.label, weight="bold")
        p.text(MARGIN_IN + 1.7, r.value)
        p.text(MARGIN_IN + 3.5, r.status or "—", color=STATUS_COLOURS.get(r.status, "#222222"),
               weight="bold" if r.status not in ("", "PASS") else "normal")
        p.y += p.line_in
        p.wrapped(r.detail, width=WIDTH - 20, color="#444444", indent="")
    p.wrapped("Volumetric error: tool tip actual minus nominal relative to the workpiece, "
              "commanded X, Y, Z with the rotary axes at zero, workpiece frame; rigid "
              "convention: " + doc.rigid_convention + ".", width=WIDTH, color="#444444")
    _head(p, "Placements")
    for n, pl in enumerate(doc.placements, 1):
        p.wrapped(f"{n} ({pl.name}): {pl.log} with {pl.artefact}: {pl.centres} centres, "
                  f"{pl.poses} poses, residual RMS {pl.residual_rms_um:.3f} µm", width=WIDTH)
    fit = doc.fit
    p.wrapped(f"Fit: residual RMS {fit.residual_rms_um:.3f} µm, {fit.iterations} iteration(s), "
              + ("converged" if fit.converged else "NOT converged")
              + (f"; degrees {degrees_text(doc)} by {doc.order.method}" if doc.order else ""),
              width=WIDTH)
    h = doc.holdout
    if h is not None:
        p.wrapped(f"Held out ({h.log}, {h.centres} centres): RMS {h.rms_before_um:.2f} → "
                  f"{h.rms_after_um:.2f} µm, max {h.max_before_um:.2f} → {h.max_after_um:.2f} "
                  "µm without → with the map", width=WIDTH)
    gone = [s.name for s in states(doc).values() if s.state == "none"]
    p.wrapped("Not observable: " + (", ".join(gone) if gone else "no whole function")
              + " (in words on page 4)", width=WIDTH, weight="bold")
    return p.y


def _page3(p: _Page, doc: LinearMapFile) -> None:
    _head(p, "Motion errors: state and size over the covered range")
    for x, s in ((0.0, "ISO 230-1"), (2.9, "state"), (4.1, "max |e|"), (4.9, "u (k=1)"),
                 (5.6, "unit")):
        p.text(MARGIN_IN + x, s, weight="bold", size=7.5)
    p.y += p.line_in
    for f in doc.functions:
        s = states(doc)[f.name]
        state = {"none": "NOT OBSERVABLE", "partly": "in part"}.get(s.state, "observable")
        cells = [(0.0, title(f)), (2.9, state),
                 (4.1, "—" if s.max_abs is None else f"{s.max_abs:.2f}"),
                 (4.9, "—" if s.u_at_max is None else f"{s.u_at_max:.2f}"), (5.6, s.unit)]
        for x, c in cells:
            p.text(MARGIN_IN + x, c, size=7.5,
                   color="#777777" if s.state == "none" else "#222222")
        p.y += p.line_in


def _page4(p: _Page, doc: LinearMapFile, bottom_in: float) -> None:
    _head(p, "Not observable")
    lines = [*unobservable_lines(doc), doc.observability.note]
    links = ", ".join(f"{k} {v.value:+.2f} ± {v.std:.2f} {'µrad' if v.unit == 'urad' else 'µm'}"
                      for k, v in doc.links.items())
    tail = [("Link errors estimated with the map", f"{links}."),
            ("Warnings", "; ".join(doc.warnings))] if doc.warnings else [
        ("Link errors estimated with the map", f"{links}.")]
    left = 0
    for k, line in enumerate(lines):
        if p.y > bottom_in - 4 * p.line_in:
            left = len(lines) - k
            break
        p.wrapped("• " + line, width=WIDTH, indent="   ")
    for head, text in tail:
        if p.y > bottom_in - 4 * p.line_in:
            left += 1
            continue
        _head(p, head)
        p.wrapped(text, width=WIDTH)
    if left:
        p.line(f"… {left} more item(s) in the HTML and JSON report", color="#444444")


def write_map_pdf(path: Path, doc: LinearMapFile, plots: dict[str, bytes | None]) -> Path:
    """Write the four A4 pages of ``doc`` to ``path``; ``plots`` are the report's own PNGs by
    key (volume, functions, slices; a missing one is left out)."""
    generated = local_time(datetime.datetime.now().timestamp())
    status = doc.figures.volumetric_max_um.status or "not judged"
    meta = {"Title": f"rumba-cnc map of the linear axes: machine {doc.machine.get('name')}: "
                     f"{status}", "Author": "rumba-cnc",
            "Subject": "volumetric map of the linear axes (ISO 230-1 motion errors)",
            "Keywords": f"{doc.machine.get('name')} map {status}",
            "CreationDate": datetime.datetime.now(datetime.UTC)}
    bottom = A4_IN[1] - FOOTER_IN
    with matplotlib.rc_context(ONE_SUBSET), PdfPages(path, metadata=meta) as pdf:
        fig = Figure(figsize=A4_IN)
        end = _page1(fig, doc)
        if plots.get("volume"):
            _stack(fig, [plots["volume"]], end + 0.1, bottom)  # type: ignore[list-item]
        _footer(fig, doc, 1, generated)
        _save(pdf, fig)
        fig = Figure(figsize=A4_IN)
        if plots.get("functions"):
            _stack(fig, [plots["functions"]], MARGIN_IN, bottom)  # type: ignore[list-item]
        _footer(fig, doc, 2, generated)
        _save(pdf, fig)
        fig = Figure(figsize=A4_IN)
        p = _Page(fig)
        if plots.get("slices"):
            _stack(fig, [plots["slices"]], MARGIN_IN, MARGIN_IN + 5.0)  # type: ignore[list-item]
            p.y = MARGIN_IN + 5.1
        _page3(p, doc)
        _footer(fig, doc, 3, generated)
        _save(pdf, fig)
        fig = Figure(figsize=A4_IN)
        _page4(_Page(fig), doc, bottom)
        _footer(fig, doc, 4, generated)
        _save(pdf, fig)
    return path
