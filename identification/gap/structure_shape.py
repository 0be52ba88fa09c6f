"""Where and how large the structure along an axis is: a cyclic or a local shape fitted to it.

Once ``structure`` has found that the residuals are a function of one axis' position, the
report says where along it, how large and on which scale. Two shapes are scanned on the
standardised residuals, one amplitude per observation channel: a cyclic one, cos/sin of
2πx/P over a grid of periods P (a least-squares periodogram of unevenly spaced positions,
Lomb 1976 / Scargle 1982), and a local one, a raised cosine of full width w centred at c over
a grid of (c, w). Each candidate is scored by what different visits agree on
(``cross_visit``), the better family by BIC (χ² form, the grid's nonlinear
parameter counted) is the located shape, and its size comes from the weighted least-squares
fit; its columns also let the visit components be estimated with the structure held fixed
(``structure_floor``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CHANNELS = ("x", "y", "z", "form")
MIN_PERIOD_MM = 6.0  # below the ball's touch spread a period reaches the centres only faintly
N_PERIODS = 90
MIN_WIDTH_MM = 12.0
N_WIDTHS = 10
CENTRE_STEP_MM = 2.5
# the test's scan (``scan_bases``): coarser, since it runs on every Monte Carlo draw
SCAN_PERIODS = 60
SCAN_WIDTHS = 8
SCAN_CENTRE_STEP = 0.25  # of the width


@dataclass(frozen=True)
class Shape:
    """A located shape along one axis (controller mm; µm in the observation channels)."""

    kind: str  # "cyclic" | "local"
    scale_mm: float  # the period, or the full width of the local shape
    centre_mm: float | None  # local: where; cyclic: None
    amplitude_um: np.ndarray  # (c,) per channel: cyclic amplitude, or the local height (signed)
    span_mm: tuple[float, float]  # the positions the balls took along the axis
    explained: float  # share of the standardised residual sum of squares it takes
    coef_um: np.ndarray | None = None  # (c, k) per channel, on ``basis``: the fitted shape

    @property
    def channel(self) -> int:
        return int(np.argmax(np.abs(self.amplitude_um)))

    @property
    def size_um(self) -> float:
        return float(np.abs(self.amplitude_um[self.channel]))

    def basis(self, q_mm: np.ndarray) -> np.ndarray:
        """(G, k) the shape's basis functions at the positions ``q_mm``."""
        if self.kind == "cyclic":
            w = 2.0 * np.pi * q_mm / self.scale_mm
            return np.stack([np.cos(w), np.sin(w)], axis=1)
        return bump(q_mm, self.centre_mm, self.scale_mm)[:, None]

    def columns(self, q_mm: np.ndarray, channels: int) -> np.ndarray:
        """(G, 4, k · channels): the basis in every live observation channel (fixed effects
        that stand for the structure when the visit components are estimated)."""
        b = self.basis(q_mm)
        out = np.zeros((len(q_mm), 4, b.shape[1] * channels))
        for ch in range(channels):
            out[:, ch, ch * b.shape[1]:(ch + 1) * b.shape[1]] = b
        return out

    def describe(self, axis: str) -> str:
        ch = CHANNELS[self.channel]
        what = f"centre {ch}" if ch != "form" else "sphere form residual"
        if self.kind == "cyclic":
            return (f"cyclic, period ≈ {self.scale_mm:.0f} mm, ≈ {self.size_um:.1f} µm "
                    f"amplitude ({what}) over {axis} {self.span_mm[0]:.0f}…{self.span_mm[1]:.0f}"
                    " mm")
        lo, hi = self.centre_mm - self.scale_mm / 2, self.centre_mm + self.scale_mm / 2
        return (f"local, ≈ {self.size_um:.1f} µm ({what}) at {axis} ≈ {self.centre_mm:.0f} mm, "
                f"over ≈ {self.scale_mm:.0f} mm ({lo:.0f}…{hi:.0f} mm)")

    def as_dict(self, axis: str | None) -> dict:
        out = {"axis": axis, "shape": self.kind, "size_um": round(self.size_um, 3),
               "channel": CHANNELS[self.channel],
               "amplitude_um": {CHANNELS[k]: round(float(v), 3)
                                for k, v in enumerate(self.amplitude_um)},
               "span_mm": [round(self.span_mm[0], 1), round(self.span_mm[1], 1)],
               "explained_fraction": round(self.explained, 3)}
        if self.kind == "cyclic":
            out["period_mm"] = round(self.scale_mm, 1)
        else:
            out |= {"centre_mm": round(self.centre_mm, 1), "width_mm": round(self.scale_mm, 1)}
        if self.coef_um is not None:  # cos, sin (cyclic) or the height (local) per channel
            out["coefficients_um"] = {CHANNELS[k]: [round(float(v), 4) for v in row]
                                      for k, row in enumerate(self.coef_um)}
        return out


def bump(q_mm: np.ndarray, centre_mm: float, width_mm: float) -> np.ndarray:
    """The raised cosine ½(1 + cos(2π(x − c)/w)) on |x − c| ≤ w/2, 0 elsewhere."""
    u = np.clip((q_mm - centre_mm) / (0.5 * width_mm), -1.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * u))


def _fit(basis: np.ndarray, r: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per candidate (…) and channel: weighted LS of ``r`` (G, c) on ``basis`` (…, G, k) with
    weights ``w`` (G, c); returns (the reduction of the weighted RSS (…), coefficients
    (…, c, k))."""
    bw = np.einsum("...gk,gc->...cgk", basis, w)
    gram = np.einsum("...cgk,...gl->...ckl", bw, basis)
    rhs = np.einsum("...cgk,gc->...ck", bw, r)
    k = basis.shape[-1]
    gram = gram + 1e-12 * np.eye(k) * np.maximum(np.trace(gram, axis1=-2, axis2=-1), 1e-30
                                                 )[..., None, None]
    coef = np.linalg.solve(gram, rhs[..., None])[..., 0]
    return np.einsum("...ck,...ck->...", coef, rhs), coef


def cross_visit(z: np.ndarray, phi: np.ndarray, visit: np.ndarray) -> np.ndarray:
    """(draws, c, m): the squared projection (φ·z)² of the residuals ``z`` (draws, G, c) on
    each unit-norm shape φ (m, G), without what each visit contributes with itself:
    (Σ_v S_v)² − Σ_v S_v², S_v = Σ_{g ∈ v} φ_g z_g — only products of different visits.
    A shape counts in so far as the visits agree on it — it comes back where the axis
    returns; one visit alone (a chip, an index error not quite removed) adds nothing."""
    d, g, c = z.shape
    zt = np.ascontiguousarray(z.transpose(0, 2, 1)).reshape(-1, g)
    i, j = np.triu_indices(g, 1)
    same = visit[i] == visit[j]
    i, j = i[same], j[same]
    own = (zt**2) @ (phi**2).T + 2.0 * ((zt[:, i] * zt[:, j]) @ (phi[:, i] * phi[:, j]).T)
    return ((zt @ phi.T) ** 2 - own).reshape(d, c, -1)


def locate(q_mm: np.ndarray, r_um: np.ndarray, sd_um: np.ndarray, live: np.ndarray,
           visit: np.ndarray) -> Shape:
    """The shape along one axis (positions ``q_mm`` (G,)) on which the visits (``visit``
    (G,) ids) agree best — the largest share of the standardised residuals between visits
    (``cross_visit``) — with its size from the weighted least-squares fit of the
    residuals ``r_um`` (G, c) by 1/``sd_um``² over the ``live`` observations."""
    w = np.where(live, 1.0 / sd_um**2, 0.0)
    z = np.where(live, r_um / sd_um, 0.0)[None]
    lo, hi = float(q_mm.min()), float(q_mm.max())
    span = max(hi - lo, 2 * MIN_PERIOD_MM)
    total = float(np.sum(z**2))
    n, c = int(live.sum()), r_um.shape[1]
    periods = np.geomspace(MIN_PERIOD_MM, span, N_PERIODS)
    red_c = cross_visit(z, _cyclic_rows(q_mm, periods), visit)[0].sum(axis=0)
    red_c = red_c[0::2] + red_c[1::2]
    i = int(np.argmax(red_c))
    ang = 2.0 * np.pi * q_mm / periods[i]
    _, coef = _fit(np.stack([np.cos(ang), np.sin(ang)], axis=1), r_um, w)
    cyc = Shape("cyclic", float(periods[i]), None, np.hypot(*coef.T), (lo, hi),
                float(red_c[i] / total) if total > 0 else 0.0, coef)
    widths = np.geomspace(MIN_WIDTH_MM, max(span, 2 * MIN_WIDTH_MM), N_WIDTHS)
    grid = [(cc, ww) for ww in widths for cc in np.arange(lo, hi + CENTRE_STEP_MM,
                                                          CENTRE_STEP_MM)]
    rows, grid = _bump_rows(q_mm, grid)
    red_l = cross_visit(z, rows, visit)[0].sum(axis=0)
    j = int(np.argmax(red_l))
    _, coef = _fit(bump(q_mm, *grid[j])[:, None], r_um, w)
    loc = Shape("local", float(grid[j][1]), float(grid[j][0]), coef[:, 0], (lo, hi),
                float(red_l[j] / total) if total > 0 else 0.0, coef)
    # BIC in χ² form on standardised residuals: −reduction + k ln n (k: the amplitudes and
    # the scanned period, or centre and width)
    bic_c = -red_c[i] + (2 * c + 1) * np.log(max(n, 2))
    bic_l = -red_l[j] + (c + 2) * np.log(max(n, 2))
    return cyc if bic_c < bic_l else loc


def _cyclic_rows(q_mm: np.ndarray, periods: np.ndarray) -> np.ndarray:
    """(2·periods, G): per period the cos/sin pair made orthonormal over the groups."""
    rows = []
    for period in periods:
        w = 2.0 * np.pi * q_mm / period
        qr, r = np.linalg.qr(np.stack([np.cos(w), np.sin(w)], axis=1))
        if abs(r[1, 1]) < 1e-9 * abs(r[0, 0]):
            qr[:, 1] = 0.0
        rows += [qr[:, 0], qr[:, 1]]
    return np.array(rows)


def _bump_rows(q_mm: np.ndarray, grid: list[tuple[float, float]]
               ) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """The unit-norm bumps of the (centre, width) grid that reach a ball, and their grid."""
    rows, kept = [], []
    for c, w in grid:
        b = bump(q_mm, c, w)
        n = np.linalg.norm(b)
        if n > 0:
            rows.append(b / n)
            kept.append((c, w))
    return np.array(rows), kept


def scan_bases(q_mm: np.ndarray) -> dict[str, tuple[np.ndarray, int]]:
    """The test's scan along one axis: {"cyclic": (rows (2·periods, G), 2), "local":
    (rows (candidates, G), 1)} — each cyclic pair orthonormal over the groups, each bump
    of unit norm — so that a candidate's share of a standardised residual is its squared
    projection."""
    lo, hi = float(q_mm.min()), float(q_mm.max())
    span = max(hi - lo, 2 * MIN_PERIOD_MM)
    widths = np.geomspace(MIN_WIDTH_MM, max(span, 2 * MIN_WIDTH_MM), SCAN_WIDTHS)
    grid = [(c, w) for w in widths for c in np.arange(lo, hi + 1e-9, SCAN_CENTRE_STEP * w)]
    return {"cyclic": (_cyclic_rows(q_mm, np.geomspace(MIN_PERIOD_MM, span, SCAN_PERIODS)), 2),
            "local": (_bump_rows(q_mm, grid)[0], 1)}
