"""The report for filing: a PDF of three A4 pages (matplotlib's PDF backend, no other dependency).

Page 1: the verdict, what to do, the audit fields, the reasons, the checks and the identified
link errors with their limits. Page 2: volumetric distortion, relocalisation vs local
distortion, and the trend of every link with its limits (when the machine has past runs).
Page 3: figures with their definitions, link errors with plain and controller names, setup
errors, validation, health, the decision rule and the approval block (``pdf_sections``).
Text is vector; the plots are the report's own PNGs, drawn once at the page's text width for
the HTML and the PDF (140 dpi, embedded without resampling). Checks beyond what fits on page 1
are counted, not drawn (the HTML and JSON hold all of them): the PDF never grows past 3 pages.
"""

from __future__ import annotations

import datetime
import io
import logging
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib
from matplotlib import image as mpimg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure
from matplotlib.patches import FancyBboxPatch
from matplotlib.text import Text

from daemon.analysis.result import Analysis
from daemon.reports import temperatures
from daemon.reports.audit import audit_rows, local_time
from daemon.reports.index_scatter import index_scatter_lines
from daemon.reports.pdf_sections import page3
from daemon.reports.plots import VERDICT_COLOURS
from daemon.store.journal import RunRow

# matplotlib subsets the embedded fonts with fontTools, which logs every table it prunes at
# INFO (~200 lines per PDF): its loggers only, so the daemon's own INFO log stays as it is
logging.getLogger("fontTools").setLevel(logging.WARNING)

A4_IN = (8.27, 11.69)
MARGIN_IN = 0.5
LINE_IN = 0.16  # one line of 8 pt text
FOOTER_IN = 0.35
FONT = 8
PAGES = 3
ONE_SUBSET = {"pdf.fonttype": 42, "ps.fonttype": 42}  # see write_pdf
NO_LIGATURES = ("-liga", "-clig")
STATUS_COLOURS = VERDICT_COLOURS


class _Page:
    """Text placed from the top of an A4 figure, line by line (inches from the top edge)."""

    margin, line_in = MARGIN_IN, LINE_IN

    def __init__(self, fig: Figure) -> None:
        self.fig, self.y = fig, MARGIN_IN

    def _xy(self, x_in: float, y_in: float) -> tuple[float, float]:
        return x_in / A4_IN[0], 1.0 - y_in / A4_IN[1]

    def text(self, x_in: float, s: str, *, size: float = FONT, dy: float = 0.0,
             **kw: Any) -> None:
        self.fig.text(*self._xy(x_in, self.y + dy), s, fontsize=size, va="top",
                      parse_math=False, **kw)

    def line(self, s: str = "", size: float = FONT, gap: float = 1.0, **kw: Any) -> None:
        self.text(MARGIN_IN, s, size=size, **kw)
        self.y += gap * LINE_IN * size / FONT

    def wrapped(self, s: str, width: int = 118, indent: str = "", **kw: Any) -> None:
        for k, part in enumerate(textwrap.wrap(s, width) or [""]):
            self.line((indent if k else "") + part, **kw)

    def rule(self) -> None:
        x0, y = self._xy(MARGIN_IN, self.y)
        x1, _ = self._xy(A4_IN[0] - MARGIN_IN, self.y)
        self.fig.add_artist(_hline(x0, x1, y))
        self.y += 0.08


def _hline(x0: float, x1: float, y: float) -> Any:
    from matplotlib.lines import Line2D

    return Line2D([x0, x1], [y, y], color="#bbbbbb", lw=0.6)


def _footer(fig: Figure, run: RunRow, page: int, generated: str) -> None:
    fig.text(0.5, 0.012, f"rumba-cnc — machine {run.machine} — run {run.id} — generated "
                         f"{generated} — page {page} of {PAGES}", ha="center", fontsize=6.5,
             color="#666666", parse_math=False)


def _page1(fig: Figure, run: RunRow, analysis: Analysis, doc: dict[str, Any],
           audit_rows: Sequence[tuple[str, str]], bottom_in: float) -> float:
    """Page 1's text; returns where it ends (inches from the top)."""
    p = _Page(fig)
    verdict = doc.get("verdict")
    status = verdict["status"] if verdict else run.state
    p.line("rumba-cnc — five-axis machine verification (RUMBA, uncalibrated ball artefact)",
           color="#555555")
    p.line(f"Machine {run.machine} — run {run.id}", size=15, gap=1.25, weight="bold")
    colour = STATUS_COLOURS.get(status, "#555555")
    x0, y0 = p._xy(MARGIN_IN, p.y + 0.42)
    fig.add_artist(FancyBboxPatch((x0, y0), 1.25 / A4_IN[0], 0.38 / A4_IN[1],
                                  boxstyle="round,pad=0.002", transform=fig.transFigure,
                                  facecolor=colour, edgecolor="none"))
    fig.text(*p._xy(MARGIN_IN + 0.625, p.y + 0.23), status, fontsize=16, weight="bold",
             color="white", ha="center", va="center", parse_math=False)
    for k, part in enumerate(textwrap.wrap(run.summary or run.reason or "", 88)[:2]):
        p.text(MARGIN_IN + 1.4, part, size=9, dy=0.06 + 0.17 * k)
    p.y += 0.55
    if doc.get("what_to_do"):
        p.wrapped("What to do: " + doc["what_to_do"], width=100, size=9.5, weight="bold",
                  color=colour)
    p.y += 0.05
    p.rule()
    for k, v in audit_rows:
        p.text(MARGIN_IN + 1.75, v)
        p.line(k, color="#444444")
    p.line(f"{analysis.touches} touches; residual RMS {analysis.residual_rms_um or 0:.2f} µm; "
           f"condition number {analysis.condition_number or 0:.3g}"
           + (f"; drift reference run {analysis.reference_run}" if analysis.reference_run
              else ""), color="#444444")
    th = analysis.thermal
    if th is not None:  # the TCP drift fitted with the links, or why it was not
        p.wrapped(("Thermal drift over the run (" + (th.shape or "") + (
            f", τ {th.tau_min:.0f} min" if th.tau_min is not None else "") + "): " + ", ".join(
            f"{a} {d.value:+.2f} ± {d.std:.2f} µm" for a, d in sorted(th.over_run_um.items())
            if d.value is not None and d.std is not None)
            + "; link errors estimated with it") if th.status == "selected" else th.message,
            width=125, color="#444444")
    # the rotary axes' indexing repeatability the link u rest on (the report's text)
    for line in index_scatter_lines(analysis):
        p.wrapped(line, width=125, color="#444444")
    if analysis.temperatures:  # the channels read during the run
        p.wrapped("Temperatures: " + "; ".join(temperatures.channel_text(n, t) for n, t in
                                                analysis.temperatures.items()),
                  width=125, color="#444444")
    p.rule()
    if verdict and verdict["reasons"]:
        p.line("Reasons", size=10, weight="bold", gap=1.2)
        for r in verdict["reasons"][:6]:
            p.wrapped("• " + r, width=125, indent="   ")
        if len(verdict["reasons"]) > 6:
            p.line(f"… and {len(verdict['reasons']) - 6} more (HTML report)")
        p.y += 0.05
    if verdict:
        _checks(p, verdict["checks"], bottom_in)
    return p.y


def _cut(text: str, n: int) -> str:
    return text if len(text) <= n else text[:n - 1] + "…"


CHECK_COLUMNS = [(0.0, "quantity", 50), (2.95, "value", 9), (3.6, "u", 7), (4.05, "unit", 5),
                 (4.5, "limit", 44), (6.85, "status", 6)]


def _checks(p: _Page, checks: list[dict[str, Any]], bottom_in: float) -> None:
    """The checks table, not-passed first; rows that do not fit are counted, not drawn."""
    p.line("Checks", size=10, weight="bold", gap=1.2)
    for x, head, _ in CHECK_COLUMNS:
        p.text(MARGIN_IN + x, head, weight="bold", size=7.5)
    p.y += LINE_IN
    rows = sorted(checks, key=lambda c: c["status"] == "PASS")
    room = max(0, int((bottom_in - p.y) / LINE_IN) - 1)
    shown = rows if len(rows) <= room else rows[:room]
    for c in shown:
        value = c["value"]
        cells = [c["quantity"], f"{value:+.2f}" if value == value else "—",
                 f"{c['std']:.2f}" if c["std"] else "", c["unit"], c["limit"], c["status"]]
        for (x, head, width), cell in zip(CHECK_COLUMNS, cells, strict=True):
            status = head == "status"
            p.text(MARGIN_IN + x, _cut(cell, width), size=7.5,
                   color=STATUS_COLOURS.get(cell, "#222222") if status else "#222222",
                   weight="bold" if status and cell != "PASS" else "normal")
        p.y += LINE_IN
    if len(shown) < len(rows):
        p.line(f"… {len(rows) - len(shown)} more checks, all PASS, in the HTML and JSON report",
               color="#444444")


def _image(fig: Figure, png: bytes, x_in: float, top_in: float, w_in: float) -> float:
    """Place a PNG ``w_in`` wide with its top ``top_in`` below the page top (embedded at its own
    resolution, not resampled); returns its height in inches."""
    img = mpimg.imread(io.BytesIO(png), format="png")
    h_in = w_in * img.shape[0] / img.shape[1]
    ax = fig.add_axes((x_in / A4_IN[0], 1.0 - (top_in + h_in) / A4_IN[1], w_in / A4_IN[0],
                       h_in / A4_IN[1]))
    ax.imshow(img, interpolation="none")
    ax.set_axis_off()
    return h_in


def _stack(fig: Figure, pngs: list[bytes], top_in: float, bottom_in: float) -> None:
    """Place ``pngs`` one below the other at the text width, shrunk together (and centred) when
    they are taller than the room between ``top_in`` and ``bottom_in``."""
    width = A4_IN[0] - 2 * MARGIN_IN
    gap = 0.12
    heights = [width * h / w for h, w in (_size(p) for p in pngs)]
    room = bottom_in - top_in - gap * (len(pngs) - 1)
    k = min(1.0, room / sum(heights))
    y = top_in
    for p in pngs:
        y += _image(fig, p, MARGIN_IN + width * (1 - k) / 2, y, width * k) + gap


def _size(png: bytes) -> tuple[int, int]:
    """(height, width) in pixels from the PNG header."""
    return int.from_bytes(png[20:24], "big"), int.from_bytes(png[16:20], "big")


def write_pdf(path: Path, run: RunRow, analysis: Analysis, doc: dict[str, Any], audit: Any,
              plots: dict[str, bytes | None], prepared_by: str = "") -> Path:
    """Write the two A4 pages of ``run`` to ``path`` (the caller has checked the path); the
    plots are the report's own PNGs by key (``report.render_plots``: distortion, cluster,
    links, trend; a missing or None one is left out)."""
    generated = local_time(datetime.datetime.now().timestamp())
    status = doc["verdict"]["status"] if doc.get("verdict") else run.state
    meta = {"Title": f"rumba-cnc report: machine {run.machine}, run {run.id}: {status}",
            "Author": "rumba-cnc", "Subject": doc.get("what_to_do") or status,
            "Keywords": f"{run.machine} {run.id} {status}",
            "CreationDate": datetime.datetime.now(datetime.UTC)}
    links = plots.get("links")
    page2 = [p for p in (plots.get(k) for k in ("distortion", "cluster", "trend")) if p]
    links_in = (A4_IN[0] - 2 * MARGIN_IN) * _ratio(links) if links else 0.0
    bottom = A4_IN[1] - FOOTER_IN
    # TrueType text (not Type 3): selectable, searchable and crisp in every viewer. One subset
    # per font: matplotlib 3.11's PDF backend sizes its subsets by *ps*.fonttype
    # (Type 3: 256 codes), so "—", "•", "→" opened a second copy of each font; at 42 the whole
    # BMP fits one subset. Ligatures ("fi") are always put in a second subset: _save drops them.
    with matplotlib.rc_context(ONE_SUBSET), PdfPages(path, metadata=meta) as pdf:
        fig = Figure(figsize=A4_IN)
        end = _page1(fig, run, analysis, doc, audit_rows(run, audit, analysis),
                     bottom - links_in - 0.15)
        if links:  # right below the checks: no blank band between text and plot
            top = min(end + 0.1, bottom - links_in)
            _stack(fig, [links], top, top + links_in)
        _footer(fig, run, 1, generated)
        _save(pdf, fig)
        fig = Figure(figsize=A4_IN)
        if page2:
            _stack(fig, page2, MARGIN_IN, bottom)
        else:
            fig.text(0.5, 0.5, "no plots: the run has no distortion, cluster or trend data",
                     ha="center")
        _footer(fig, run, 2, generated)
        _save(pdf, fig)
        fig = Figure(figsize=A4_IN)  # the HTML's sections below the plots, the approval block
        page3(_Page(fig), analysis, doc, audit, prepared_by, generated[:10])
        _footer(fig, run, 3, generated)
        _save(pdf, fig)
    return path


def _save(pdf: PdfPages, fig: Figure) -> None:
    """One page, its text without ligatures (each would open a second subset of its font)."""
    for t in fig.findobj(Text):
        t.set_fontfeatures(NO_LIGATURES)
    pdf.savefig(fig)


def _ratio(png: bytes) -> float:
    h, w = _size(png)
    return h / w
