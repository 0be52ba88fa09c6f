"""The report's plots, drawn into a given figure (a PNG for the HTML, a region of an A4 page for
the PDF): volumetric distortion vectors per pose (thesis Fig 3.10), relocalisation vs local
distortion per pose (thesis §4.4), link errors with 2u bars and their limits, and the trend of
every link over past runs on its own unit axis with its limits.

Every axis names its unit; no axis uses an offset (``+1.104e2``): a 0.1 µm change must not look
like a jump. Untrusted text (names) is drawn with ``parse_math=False``.
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure, SubFigure
from matplotlib.gridspec import GridSpec
from matplotlib.lines import Line2D

from daemon.analysis.result import Analysis
from daemon.machines.tolerances import Tolerances
from daemon.reports.trend import UNITS, limit_for, trend_series
from daemon.store.journal import TrendPoint

VERDICT_COLOURS = {"PASS": "#1b873f", "WARN": "#c77700", "FAIL": "#c62828", "ERROR": "#6a1b9a"}
WARN_STYLE = {"color": "#c77700", "linestyle": "--", "linewidth": 1.0}
FAIL_STYLE = {"color": "#c62828", "linestyle": "-", "linewidth": 1.0}
Canvas = Figure | SubFigure


WIDTH_IN = 7.2  # the text width of an A4 page: one drawing serves the HTML and the PDF
DPI = 140  # 1008 px wide in the browser; 140 dpi on paper


def png(draw: Callable[..., bool], height_in: float, *args: Any) -> bytes | None:
    """``draw(fig, *args)`` into a new figure ``WIDTH_IN`` × ``height_in`` → PNG bytes, or None
    when it drew nothing."""
    with matplotlib.rc_context({"font.size": 8, "axes.titlesize": 9, "figure.titlesize": 10,
                                "legend.fontsize": 7, "xtick.labelsize": 7,
                                "ytick.labelsize": 7}):
        # no layout engine: every plot sets its own margins, and a figure with an engine
        # (even a switched-off one) is drawn twice by savefig
        fig = Figure(figsize=(WIDTH_IN, height_in))
        if not draw(fig, *args):
            return None
        FigureCanvasAgg(fig)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _plain(ax: Axes) -> None:
    ax.ticklabel_format(axis="y", useOffset=False, style="plain")
    ax.grid(alpha=0.3)


def _nice(x: float) -> float:
    """A round reference length (1, 2 or 5 × 10^n) close to ``x``."""
    if x <= 0:
        return 1.0
    e = math.floor(math.log10(x))
    return min((m * 10.0**e for m in (1, 2, 5, 10)), key=lambda v: abs(math.log(v / x)))


def _visit_labels(items: Sequence[Any]) -> list[str]:
    """``pose`` (and ``#visit`` when a pose is probed more than once, e.g. the drift check)."""
    repeats: dict[int, int] = {}
    for c in items:
        repeats[c.pose] = repeats.get(c.pose, 0) + 1
    out = []
    for c in items:
        visit = f" #{c.repeat + 1}" if repeats[c.pose] > 1 else ""
        out.append(f"{c.pose}{visit}\nB{c.b_deg:g}\nC{c.c_deg:g}")
    return out


def draw_distortion(fig: Canvas, analysis: Analysis,
                    centres: dict[tuple[int, str], Sequence[float]], with_3d: bool = True) -> bool:
    """Arrows of the volumetric distortion (setup errors removed) at every measured centre
    (``centres``: (pose, ball) → x y z mm), magnified; one colour per pose, a legend of the
    colours and a reference arrow in µm in every panel (thesis Fig 3.10)."""
    vol = [v for v in analysis.volumetric
           if (v.pose, v.ball) in centres and v.error_um is not None]
    if not vol:
        return False
    pts = np.array([centres[(v.pose, v.ball)] for v in vol], float)
    err = np.array([v.error_um for v in vol], float)
    poses = sorted({v.pose for v in vol})
    span = float(np.ptp(pts, axis=0).max()) or 1.0
    emax = float(np.linalg.norm(err, axis=1).max()) or 1.0
    mag = 0.15 * span / (emax * 1e-3)  # the longest arrow is 15 % of the cloud
    vec = err * 1e-3 * mag
    ref_um = _nice(emax / 2)
    cmap = matplotlib.colormaps["tab20"]
    colour = {p: cmap(i % 20) for i, p in enumerate(poses)}
    colours = [colour[v.pose] for v in vol]
    planes = [(0, 1, "XY"), (1, 2, "YZ"), (0, 2, "XZ")]
    grid = (2, 2) if with_3d else (1, 3)
    legend_rows = math.ceil(len(poses) / 5)
    gs = _fixed_margins(fig, grid, top_in=0.6, bottom_in=0.55 + 0.16 * legend_rows,
                        wspace=0.3, hspace=0.45, right_in=0.35)
    cells = [gs[k // grid[1], k % grid[1]] for k in range(grid[0] * grid[1])]
    for k, (i, j, name) in enumerate(planes):
        ax = fig.add_subplot(cells[k])
        ax.scatter(pts[:, i], pts[:, j], s=6, c=colours)
        q = ax.quiver(pts[:, i], pts[:, j], vec[:, i], vec[:, j], color=colours, angles="xy",
                      scale_units="xy", scale=1, width=0.005)
        # the reference arrow, right of the panel title: its length is ref_um at this scale
        ax.quiverkey(q, 0.97, 1.045, ref_um * 1e-3 * mag, f"{ref_um:g} µm", labelpos="W",
                     coordinates="axes", color="black", fontproperties={"size": 7})
        ax.set_xlabel(f"{name[0]} / mm")
        ax.set_ylabel(f"{name[1]} / mm")
        ax.set_title(f"{name} plane", loc="left")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    if with_3d:
        ax3 = fig.add_subplot(cells[3], projection="3d")
        ax3.quiver(pts[:, 0], pts[:, 1], pts[:, 2], vec[:, 0], vec[:, 1], vec[:, 2],
                   colors=colours, arrow_length_ratio=0.2)
        ax3.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=6, c=colours)
        ax3.set_xlabel("X / mm")
        ax3.set_ylabel("Y / mm")
        ax3.set_zlabel("Z / mm")
        ax3.set_title(f"3D, same scale: {ref_um:g} µm ≙ {ref_um * 1e-3 * mag:.0f} mm",
                      loc="left")
    pose_deg = {v.pose: (v.b_deg, v.c_deg) for v in vol}
    handles = [Line2D([], [], marker="o", ls="", color=colour[p],
                      label=f"pose {p} (B{pose_deg[p][0]:g} C{pose_deg[p][1]:g})")
               for p in poses]
    fig.legend(handles=handles, loc="lower center", ncols=min(len(handles), 5),
               title="arrow and dot colour = pose (B, C in °)", title_fontsize=7,
               borderaxespad=0.2)
    fig.suptitle(f"Volumetric distortion per pose (setup errors removed): arrows ×{mag:.0f}, "
                 f"largest {emax:.1f} µm")
    return True


def draw_cluster(fig: Canvas, analysis: Analysis) -> bool:
    """Per pose visit: |linear relocalisation| and the largest local distortion on a µm axis,
    |angular relocalisation| on a µrad axis — rotary errors relocate, linear-axis errors also
    distort (thesis §4.4, Table 4.2)."""
    cl = [c for c in analysis.cluster if c.linear_um is not None and c.angular_urad is not None]
    if not cl:
        return False
    x = np.arange(len(cl))
    lin = [math.hypot(*c.linear_um) for c in cl]  # type: ignore[misc]
    ang = [math.hypot(*c.angular_urad) for c in cl]  # type: ignore[misc]
    loc = [max((math.hypot(*v) for v in c.local_um.values()), default=0.0)  # type: ignore[misc]
           for c in cl]
    gs = _fixed_margins(fig, (2, 1), top_in=0.4, bottom_in=0.75, wspace=0.0, hspace=0.12,
                        right_in=1.75, height_ratios=[3, 2])  # legends right of the bars
    top = fig.add_subplot(gs[0])
    bottom = fig.add_subplot(gs[1], sharex=top)
    top.tick_params(labelbottom=False)
    w = 0.38
    top.bar(x - w / 2, lin, w, label="linear relocalisation |D|", color="#1565c0")
    top.bar(x + w / 2, loc, w, label="local distortion, largest", color="#ef6c00")
    top.set_ylabel("µm")
    top.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), borderaxespad=0)
    bottom.bar(x, ang, 2 * w, label="angular relocalisation |R|", color="#6a1b9a")
    bottom.set_ylabel("µrad")
    bottom.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), borderaxespad=0)
    bottom.set_xticks(x, _visit_labels(cl), fontsize=6)
    bottom.set_xlabel("pose (#n: n-th visit of a pose probed again), its B and C in °")
    for ax in (top, bottom):
        _plain(ax)
        ax.set_ylim(bottom=0)
    fig.suptitle("Relocalisation vs local distortion per pose (cluster analysis, thesis §4.4)")
    return True


def _limit_lines(ax: Axes, warn: float | None, fail: float | None, two_sided: bool,
                 xmin: float = 0.0, xmax: float = 1.0) -> None:
    for val, style in ((warn, WARN_STYLE), (fail, FAIL_STYLE)):
        if val is not None:
            for v in (val, -val) if two_sided else (val,):
                ax.axhline(v, xmin, xmax, **style)


def draw_links(fig: Canvas, analysis: Analysis, tol: Tolerances | None) -> bool:
    """Identified link errors ± 2u, rotations and translations on their own unit axes, each with
    its warn (dashed) and fail (solid) limits."""
    links = analysis.links
    if not links:
        return False
    groups = [(u, [n for n in sorted(links) if links[n].unit == u]) for u in ("urad", "um")]
    groups = [(u, names) for u, names in groups if names]
    gs = _fixed_margins(fig, (1, len(groups)), top_in=0.55, bottom_in=0.55, wspace=0.25,
                        hspace=0.0, width_ratios=[max(len(n), 2) for _, n in groups])
    axes = [fig.add_subplot(gs[0, k]) for k in range(len(groups))]
    for ax, (unit, names) in zip(axes, groups, strict=True):
        x = np.arange(len(names))
        ax.errorbar(x, [links[n].value for n in names],
                    yerr=[2 * (links[n].std or 0.0) for n in names], fmt="o", color="#0d47a1",
                    capsize=5, label="estimate ± 2u")
        for i, n in enumerate(names):
            lim = limit_for(n, unit, tol)
            if lim is not None:
                for val, style in ((lim.warn, WARN_STYLE), (lim.fail, FAIL_STYLE)):
                    if val is not None:
                        ax.hlines([val, -val], i - 0.35, i + 0.35, colors=style["color"],
                                  linestyles=style["linestyle"])
        ax.axhline(0, color="grey", lw=0.8)
        ax.set_xticks(x, names)
        ax.set_xlim(-0.6, len(names) - 0.4)
        ax.set_ylabel(UNITS[unit])
        ax.set_title("Rotations" if unit == "urad" else "Translations", loc="left")
        _plain(ax)
    fig.legend(handles=[Line2D([], [], marker="o", color="#0d47a1", label="estimate ± 2u"),
                        Line2D([], [], **WARN_STYLE, label="warn limit"),
                        Line2D([], [], **FAIL_STYLE, label="fail limit")],
               loc="lower center", ncols=3, borderaxespad=0.2)
    fig.suptitle("Identified link errors (ISO 230-1)")
    return True


def _fixed_margins(fig: Canvas, grid: tuple[int, int], top_in: float, bottom_in: float,
                   wspace: float, hspace: float, left_in: float = 0.6,
                   right_in: float = 0.1, **ratios: Any) -> GridSpec:
    """A grid with its margins fixed in inches, the layout engine off (see ``_fixed_grid``)."""
    w_in, h_in = (fig.get_size_inches() if isinstance(fig, Figure)
                  else fig.figure.get_size_inches())
    if isinstance(fig, Figure) and fig.get_layout_engine() is not None:
        fig.set_layout_engine("none")
    return fig.add_gridspec(*grid, left=left_in / w_in, right=1 - right_in / w_in,
                            top=1 - top_in / h_in, bottom=bottom_in / h_in, wspace=wspace,
                            hspace=hspace, **ratios)


def _fixed_grid(fig: Canvas, nrows: int) -> dict[str, float]:
    """The trend's panel grid in fixed margins (inches → figure fractions), its layout engine
    switched off: constrained layout over ~20 panels costs as much as drawing them twice over
    (the report in ≤ 2 s). Room for the title on top, a two-line panel title per
    row, the date ticks and the legend at the bottom."""
    w_in, h_in = (fig.get_size_inches() if isinstance(fig, Figure)
                  else fig.figure.get_size_inches())
    if isinstance(fig, Figure) and fig.get_layout_engine() is not None:
        fig.set_layout_engine("none")
    top_in, bottom_in, gap_in = 0.62, 0.62, 0.5  # title; ticks + legend; between rows
    axes_in = max((h_in - top_in - bottom_in - gap_in * (nrows - 1)) / nrows, 0.3)
    return {"left": 0.6 / w_in, "right": 1 - 0.08 / w_in, "top": 1 - top_in / h_in,
            "bottom": bottom_in / h_in, "wspace": 0.42, "hspace": gap_in / axes_in}


def draw_trend(fig: Canvas, trend: Sequence[TrendPoint], tol: Tolerances | None,
               ncols: int = 3) -> bool:
    """One panel per link error (and the largest volumetric distortion), each on its own unit
    axis with its limits: the axis spans the data and the fail limit, so a value's distance to
    its limit reads at a glance; the last value and its change since the previous run are
    written in the panel (a drift of a few µm stays legible even next to a 250 µm limit)."""
    if len(trend) < 2:
        return False
    data = trend_series(trend, tol)
    series = data["series"]
    x = np.arange(len(trend))
    dots = [VERDICT_COLOURS.get(t.verdict, "grey") for t in trend]
    nrows = math.ceil(len(series) / ncols)
    axes = fig.subplots(nrows, ncols, sharex=True, squeeze=False,
                        gridspec_kw=_fixed_grid(fig, nrows)).ravel()
    for ax, s in zip(axes, series, strict=False):
        ys = np.array([np.nan if v is None else v for v in s["values"]], float)
        us = np.array([0.0 if v is None else 2 * v for v in s["std"]], float)
        ax.errorbar(x, ys, yerr=us, color="#455a64", lw=1, capsize=2, zorder=2)
        ax.scatter(x, ys, c=dots, s=14, zorder=3)
        _limit_lines(ax, s["warn"], s["fail"], s["two_sided"])
        span = max([abs(v) for v in ys[np.isfinite(ys)]] + [s["fail"] or s["warn"] or 0.0])
        span = 1.12 * (span or 1.0)
        ax.set_ylim(-span if s["two_sided"] else 0.0, span)
        if s["two_sided"]:
            ax.axhline(0, color="grey", lw=0.6)
        ax.set_ylabel(s["unit"])
        ax.set_title(s["name"], loc="left", fontweight="bold")
        good = np.nonzero(np.isfinite(ys))[0]
        if good.size:  # the number behind the dot, and the drift a dot cannot show
            last = f"{ys[good[-1]]:+.1f} {s['unit']}"
            if good.size > 1:  # on a second line: the name on the left keeps its room
                last += f"\nΔ{ys[good[-1]] - ys[good[-2]]:+.1f}"
            ax.set_title(last, loc="right", fontsize=7)
        _plain(ax)
    for ax in axes[len(series):]:
        ax.set_visible(False)
    step = math.ceil(len(trend) / 6)  # at most 6 date labels: more overlap at 7.2 in
    ticks = x[::step]
    for ax in axes[-ncols:]:
        ax.set_xticks(ticks, [time.strftime("%m-%d\n%H:%M", time.localtime(trend[i].started_at))
                              for i in ticks], fontsize=6)
    handles = [Line2D([], [], marker="o", ls="", color=c, label=v)
               for v, c in VERDICT_COLOURS.items()]
    handles += [Line2D([], [], **WARN_STYLE, label="warn limit"),
                Line2D([], [], **FAIL_STYLE, label="fail limit")]
    fig.legend(handles=handles, loc="lower center", ncols=6, borderaxespad=0.2)
    fig.suptitle(f"Trend, last {len(trend)} runs — dot colour: verdict; bars: ± 2u; "
                 "top right: last value, Δ since the run before")
    return True
