"""The map report's plots (drawn into a given figure, as ``plots``): the 18 motion errors over
their covered ranges with their 2u bands ("not observable" panels hatched and empty, never a
curve), the volumetric error vector field on three orthogonal slices through the middle of the
covered box (arrows to a stated scale), and the covered volume with each placement's share.

Every axis names its unit; untrusted text (names) is drawn with ``parse_math=False``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import product

import matplotlib
import numpy as np
from matplotlib.colors import Normalize

from contracts.linear_map import LinearMapFile
from daemon.reports.map_text import function_state, short, unit_text
from daemon.reports.plots import Canvas, _fixed_margins, _nice

ROWS = "XYZABC"  # the error direction: translations, then rotations about X, Y, Z
BAND = "#9ecae1"
CURVE = "#08519c"
NONE_FACE = "#f0f0f0"
PLACEMENT_COLOURS = ("#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02")


@dataclass(frozen=True)
class Slice:
    """One plane through the covered box: in-plane axes ``i``, ``j`` (0 X, 1 Y, 2 Z), the
    normal axis ``k`` held at ``at_mm``; commanded points and their error (µm, workpiece
    frame, rigid convention) and its u."""

    i: int
    j: int
    k: int
    at_mm: float
    points_mm: np.ndarray  # (N, 3)
    error_um: np.ndarray  # (N, 3)
    u_um: np.ndarray  # (N, 3)

    @property
    def name(self) -> str:
        return "XYZ"[self.i] + "XYZ"[self.j]


def draw_functions(fig: Canvas, doc: LinearMapFile) -> bool:
    """6 × 3 panels: column = the moving axis, row = the error direction (EXX in column X row
    X). An observable function: its value with the 2u band over the covered range; a function
    the data do not determine: a hatched panel saying so."""
    by_name = {f.name: f for f in doc.functions}
    if not by_name:
        return False
    gs = _fixed_margins(fig, (6, 3), top_in=0.75, bottom_in=0.45, wspace=0.28, hspace=0.6,
                        left_in=0.7, right_in=0.12)
    for r, d in enumerate(ROWS):
        for c, a in enumerate("XYZ"):
            ax = fig.add_subplot(gs[r, c])
            f = by_name.get(f"E{d}{a}")
            if f is None:
                ax.set_axis_off()
                continue
            st = function_state(doc, f)
            ax.set_title(f.name + ": " + short(f) + (" (in part)" if st.state == "partly"
                                                     else ""), loc="left", fontsize=7,
                         parse_math=False)
            x = np.asarray(f.x_mm)
            ax.set_xlim(x.min(), x.max())
            if st.state == "none":
                ax.set_facecolor(NONE_FACE)
                ax.fill_between(x, 0, 1, transform=ax.get_xaxis_transform(), hatch="///",
                                facecolor="none", edgecolor="#bdbdbd", linewidth=0)
                ax.text(0.5, 0.5, "not observable", transform=ax.transAxes, ha="center",
                        va="center", fontsize=8, weight="bold", color="#555555",
                        parse_math=False)
                ax.set_yticks([])
            else:
                v, u = np.asarray(f.value), np.asarray(f.u)
                ax.fill_between(x, v - 2 * u, v + 2 * u, color=BAND, linewidth=0,
                                label="±2u (k=2)")
                ax.plot(x, v, color=CURVE, lw=1.2, label="estimate")
                ax.axhline(0.0, color="#888888", lw=0.5)
                ax.ticklabel_format(axis="y", useOffset=False, style="plain")
                ax.grid(alpha=0.3)
            if c == 0:
                ax.set_ylabel(unit_text(f.unit))
            if r == len(ROWS) - 1:
                ax.set_xlabel(f"{a} commanded / mm")
    fig.suptitle("Motion errors of the linear axes (ISO 230-1) over their covered ranges: "
                 "estimate with its ±2u band (k=2)\n(in part): a degree of it is held by "
                 "another parameter (named in the table); the curve is the part the data "
                 "determine", fontsize=8.5)
    return True


def slices(doc: LinearMapFile, n: int, predict: object) -> list[Slice]:
    """Three orthogonal planes through the middle of the covered box, ``n`` × ``n`` points
    each; ``predict(points) → (error_um, u_um)`` (the map's own prediction)."""
    box = {a.axis: a.range_mm for a in doc.basis.axes}
    mid = [0.5 * (box[a][0] + box[a][1]) for a in "XYZ"]
    out = []
    for i, j, k in ((0, 1, 2), (0, 2, 1), (1, 2, 0)):
        gi = np.linspace(*box["XYZ"[i]], n)
        gj = np.linspace(*box["XYZ"[j]], n)
        pts = np.zeros((n * n, 3))
        pts[:, i] = np.repeat(gi, n)
        pts[:, j] = np.tile(gj, n)
        pts[:, k] = mid[k]
        err, u = predict(pts)  # type: ignore[operator]
        out.append(Slice(i, j, k, mid[k], pts, np.asarray(err), np.asarray(u)))
    return out


def arrow_scale(sl: Sequence[Slice]) -> tuple[float, float]:
    """(mm of arrow per µm of error, reference arrow µm): the longest in-plane arrow of all
    three slices fills 90 % of the smallest grid spacing; one scale for all three."""
    emax = max(float(np.linalg.norm(s.error_um[:, [s.i, s.j]], axis=1).max()) for s in sl)
    emax = emax or 1.0
    n = math.isqrt(len(sl[0].points_mm))
    spacing = min(float(np.ptp(s.points_mm[:, a])) / max(n - 1, 1) for s in sl
                  for a in (s.i, s.j)) or 1.0
    return 0.9 * spacing / emax, _nice(emax / 2)


def draw_slices(fig: Canvas, sl: Sequence[Slice]) -> bool:
    """Arrows of the in-plane error components on each slice (one scale for all, stated, with
    a reference arrow) over the out-of-plane component in colour; the covered box's section
    dashed. Three panels in a 2 × 2 grid, the fourth holds the scale and the colour bar."""
    if not sl:
        return False
    mag, ref_um = arrow_scale(sl)
    cmax = max(float(np.abs(s.error_um[:, s.k]).max()) for s in sl) or 1.0
    norm = Normalize(-cmax, cmax)
    cmap = matplotlib.colormaps["coolwarm"]
    gs = _fixed_margins(fig, (2, 2), top_in=0.45, bottom_in=0.5, wspace=0.3, hspace=0.38,
                        left_in=0.65, right_in=0.15)
    for c, s in enumerate(sl[:3]):
        ax = fig.add_subplot(gs[c // 2, c % 2])
        p, e = s.points_mm, s.error_um
        n = math.isqrt(len(p))
        gi, gj = p[:, s.i].reshape(n, n), p[:, s.j].reshape(n, n)
        ax.contourf(gi, gj, e[:, s.k].reshape(n, n), levels=np.linspace(-cmax, cmax, 21),
                    cmap=cmap, norm=norm, alpha=0.85)
        lo_i, hi_i = gi.min(), gi.max()
        lo_j, hi_j = gj.min(), gj.max()
        ax.plot([lo_i, hi_i, hi_i, lo_i, lo_i], [lo_j, lo_j, hi_j, hi_j, lo_j], ls="--",
                lw=0.8, color="#444444")
        q = ax.quiver(p[:, s.i], p[:, s.j], e[:, s.i] * mag, e[:, s.j] * mag, color="black",
                      angles="xy", scale_units="xy", scale=1, width=0.005)
        ax.quiverkey(q, 0.98, 1.05, ref_um * mag, f"{ref_um:g} µm", labelpos="W",
                     coordinates="axes", color="black", fontproperties={"size": 7})
        ax.set_xlabel(f"{'XYZ'[s.i]} / mm")
        ax.set_ylabel(f"{'XYZ'[s.j]} / mm")
        ax.set_title(f"{s.name} plane at {'XYZ'[s.k]} = {round(s.at_mm)} mm", loc="left",
                     fontsize=8)
        pad_i, pad_j = 0.08 * (hi_i - lo_i or 1.0), 0.08 * (hi_j - lo_j or 1.0)
        ax.set_xlim(lo_i - pad_i, hi_i + pad_i)
        ax.set_ylim(lo_j - pad_j, hi_j + pad_j)
        ax.set_aspect("equal", adjustable="box")
    cell = fig.add_subplot(gs[1, 1])
    cell.set_axis_off()
    cell.text(0.0, 0.95, f"Arrows: in-plane components, one scale\n"
                         f"for all three slices: 1 µm ≙ {mag:.2f} mm\n"
                         f"(reference arrow {ref_um:g} µm above each panel).\n"
                         "Colour: the out-of-plane component.\n"
                         "Dashed: the covered box's section.\n"
                         "Commanded X, Y, Z, rotary axes at zero;\n"
                         "components in the workpiece frame.",
              transform=cell.transAxes, va="top", fontsize=7.5, parse_math=False)
    cax = cell.inset_axes((0.05, 0.12, 0.85, 0.08))
    cb = fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap), cax=cax,
                      orientation="horizontal")
    cb.set_label("out-of-plane component / µm", fontsize=7)
    fig.suptitle("Volumetric error on three slices through the middle of the covered box "
                 "(rigid convention)", fontsize=9)
    return True


def _edges(lo: Sequence[float], hi: Sequence[float]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The 12 edges of the box [lo, hi] as pairs of corners."""
    corners = [np.array([(lo, hi)[b][a] for a, b in enumerate(bits)])
               for bits in product((0, 1), repeat=3)]
    return [(p, q) for ia, p in enumerate(corners) for q in corners[ia + 1:]
            if int(np.sum(p != q)) == 1]


def draw_volume(fig: Canvas, doc: LinearMapFile) -> bool:
    """The covered box (the map's domain) in 3D, each placement's ball-centre range inside it,
    and where the largest volumetric error lies."""
    box = {a.axis: a.range_mm for a in doc.basis.axes}
    if set(box) != set("XYZ"):
        return False
    lo = [box[a][0] for a in "XYZ"]
    hi = [box[a][1] for a in "XYZ"]
    gs = _fixed_margins(fig, (1, 1), top_in=0.35, bottom_in=0.15, wspace=0.0, hspace=0.0,
                        left_in=0.1, right_in=2.6)
    ax = fig.add_subplot(gs[0, 0], projection="3d")
    for p, q in _edges(lo, hi):
        ax.plot(*zip(p, q, strict=True), color="#222222", lw=1.4)
    handles = [matplotlib.lines.Line2D([], [], color="#222222", lw=1.4,
                                       label="covered box (map domain)")]
    for n, pl in enumerate(doc.placements):
        colour = PLACEMENT_COLOURS[n % len(PLACEMENT_COLOURS)]
        plo = [pl.covered_mm[a][0] for a in "XYZ"]
        phi = [pl.covered_mm[a][1] for a in "XYZ"]
        for p, q in _edges(plo, phi):
            ax.plot(*zip(p, q, strict=True), color=colour, lw=0.9, ls="--")
        handles.append(matplotlib.lines.Line2D([], [], color=colour, lw=0.9, ls="--",
                                               label=f"placement {n + 1}: ball centres"))
    at = doc.figures.volumetric_max_um.at_mm
    if at:
        ax.scatter(*at, color="#c62828", s=30, depthshade=False)
        handles.append(matplotlib.lines.Line2D(
            [], [], marker="o", ls="", color="#c62828",
            label=f"largest error {doc.figures.volumetric_max_um.value_um:.1f} µm"))
    ax.set_xlabel("X / mm")
    ax.set_ylabel("Y / mm")
    ax.set_zlabel("Z / mm")
    ax.set_box_aspect([max(h - lo_, 1e-3) for lo_, h in zip(lo, hi, strict=True)])
    fig.legend(handles=handles, loc="center right", fontsize=7, borderaxespad=0.4)
    fig.suptitle("Covered volume (commanded X, Y, Z, rotary axes at zero)", fontsize=9)
    return True
