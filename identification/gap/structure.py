"""Structure along a linear axis in the gap's residuals, tested before any scatter is credited.

Per-visit scatter and a systematic error of a linear axis leave different signatures
(METHOD.md §6; the visit model of ``identification.visit_scatter``): an index error moves all
balls of one visit together, rigidly, by the same rotation whatever their positions, and it does
not come back when the axes return to a position at another visit; a pitch error of the screw, a
local bump of a guideway or any other function of the axis position moves each ball by what the
axis does *where that ball is*, and it does come back there. REML estimated on the twin's
residuals cannot tell the second from the independent centre scatter of a ball visit (a pattern
that changes from ball to ball looks random to it): that component takes the error up and the
floor rises to meet the gap.

The test works on the generalised-least-squares residuals of the twin on every group, training
and held-out together, under the run's scatter components, with each visit's best rigid index
displacement (its BLUP) removed and each observation standardised and winsorised at ±3.5
(one visit's gross residual, a chip below what the outlier test names, is no shape of an
axis). Per controller axis a ∈ {X, Y, Z} and observation channel (centre x, y, z, form
residual: an error reaches them differently — a pitch error's local slope moves the fitted
radius, hence the centre along the spindle, more than the centre along the axis), three
statistics:

* neighbours: the mean product of the residuals of ball visits from *different* indexations
  whose centres lie within h of each other along a (``LAGS_MM``), over the mean square — a
  Moran's I restricted to the pairs the visit model cannot correlate (Moran 1950, Biometrika
  37:17; Cliff & Ord 1981, "Spatial Processes", ch. 1-2; the short-lag end of the
  semivariogram, Cressie 1993 §2.2): zero under the visit model whatever the size of its
  components, positive for any function of the position smoother than h;
* cyclic: the largest share of the channel's sum of squares one sinusoid of the position
  takes between visits (the squared projection without each visit's products with itself:
  a shape counts as far as different visits agree on it), over periods from the touch spread
  to the span (a least-squares periodogram of
  unevenly spaced positions, Lomb 1976, Astrophys. Space Sci. 39:447; Scargle 1982, ApJ
  263:835) — a smooth/periodic regression on the axis coordinate, the pitch error's matched
  filter;
* local: the same for one raised-cosine bump, over centres and widths (a scan statistic).

Their null distribution is a Monte Carlo test under the fitted visit model (Besag & Diggle
1977, Appl. Statist. 26:327): ``DRAWS`` residual vectors drawn from the model with the run's
components, projected off the same fixed columns and treated the same way, so the leverage of
the twin, the held-out groups and the index scatter are all in it; the statistics are shares
and correlations, free of the components' scale. Each is standardised by its Monte Carlo mean
and spread; the largest over the axes, channels, lags and shapes is the test statistic, the
Monte Carlo distribution of that maximum its reference — the single-step max-T adjustment of
Westfall & Young (1993, "Resampling-Based Multiple Testing" §2.5), which holds the family-wise
level ``ALPHA`` over all of them and gives each axis an adjusted p-value. The draws come from a
fixed seed: a log always gives the same answer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.gap.data import Groups, visit_ids
from identification.gap.linear import Problem, live
from identification.gap.structure_shape import Shape, cross_visit, locate, scan_bases
from identification.visit_scatter import VisitBlocks, arrange, covariance

ALPHA = 0.01  # family-wise level over the axes, channels, lags and shapes
LAGS_MM = (6.0, 12.0, 24.0)  # neighbours along the axis
MIN_GROUPS = 8  # fewer ball visits hold no pattern along an axis
CLIP = 3.5  # standardised residuals are winsorised here (Hampel's 3.5σ, as data.REJECT_Z)
DRAWS = 500  # Monte Carlo residual vectors: p-values to 0.002
MIN_PAIRS = 5  # an (axis, lag) with fewer neighbour pairs is not tested
SEED = 2301  # the Monte Carlo draws' fixed seed (a log always gives the same answer)
RANK_RCOND = 1e-9
AXES = "XYZ"


@dataclass
class Structure:
    """The test's outcome: family-wise p, per-axis adjusted p and z, and the located shape."""

    p_value: float
    axes_p: dict[str, float]
    axes_z: dict[str, float]
    axis: str | None  # the axis with the largest statistic
    lag_mm: float | None
    shape: Shape | None  # located along ``axis`` when found
    fixed: tuple[str, ...] = ()  # effects held fixed besides the twin (labels)
    draws: int = DRAWS
    others: dict[str, Shape] = field(default_factory=dict)  # other axes significant alone

    @property
    def found(self) -> bool:
        return self.p_value < ALPHA

    def as_dict(self) -> dict:
        out = {"found": self.found, "p_value": float(f"{self.p_value:.3g}"), "alpha": ALPHA,
               "axes": {a: {"p_value": float(f"{p:.3g}"), "z": round(self.axes_z[a], 2)}
                        for a, p in self.axes_p.items()},
               "axis": self.axis if self.found else None,
               "lag_mm": self.lag_mm if self.found else None,
               "with_effects": list(self.fixed), "draws": self.draws,
               "test": "Monte Carlo max-T over axes, channels, neighbour lags and shapes of "
                       "the neighbour correlation of residuals from different visits and "
                       "the largest cyclic and local shape along each axis (rigid index "
                       "displacement removed)",
               "message": self.message()}
        if self.found and self.shape is not None:
            out["located"] = self.shape.as_dict(self.axis)
            out["also_located"] = [sh.as_dict(a) for a, sh in self.others.items()]
        return out

    def shapes(self) -> dict[str, Shape]:
        """Every located shape by axis, the main one first."""
        main = {self.axis: self.shape} if self.found and self.shape is not None else {}
        return main | self.others

    def message(self) -> str:
        ps = ", ".join(f"{a} p = {p:.2g}" for a, p in self.axes_p.items())
        fixed = f" with {', '.join(self.fixed)} fixed" if self.fixed else ""
        if not self.found:
            return (f"no structure along X, Y or Z{fixed} ({ps}; α = {ALPHA:g} over the "
                    "axes): what the visits leave is not a function of an axis' position")
        where = self.shape.describe(self.axis) if self.shape is not None else ""
        others = [f"{a}: {sh.describe(a)}" for a, sh in self.others.items()]
        return (f"structure along {self.axis}{fixed}{': ' + where if where else ''} (p = "
                f"{self.p_value:.2g} over X, Y, Z; {ps})"
                + (f"; also along {'; '.join(others)}" if others else "")
                + f" — ball visits of different indexations follow one function of the "
                f"{self.axis} position, which comes back where the axis returns (a pitch "
                "error, a local defect of a guideway): not visit scatter")


def _blocks(problem: Problem, groups: Groups, vs, cols: np.ndarray) -> VisitBlocks:
    cov = np.zeros((len(groups), 4, 4))
    cov[:, :3, :3] = groups.centre_cov_um2
    cov[:, 3, 3] = groups.sigma_touch_um**2
    return arrange(problem.y_um, cols, cov, vs.z, visit_ids(groups), live(problem))


class _Residuals:
    """The model's residual map for whitened vectors: project off the fixed columns, back to
    µm, the rigid index displacement (BLUP) removed, per group (…, G, c)."""

    def __init__(self, b: VisitBlocks, theta: np.ndarray, n_groups: int) -> None:
        self.b, self.g_n = b, n_groups
        self.chol = np.linalg.cholesky(covariance(b, theta))
        eye = np.broadcast_to(np.eye(self.chol.shape[1]), self.chol.shape)
        self.w = np.linalg.solve(self.chol, eye)
        xw = np.einsum("vij,vjp->vip", self.w, b.x).reshape(-1, b.x.shape[2])
        u, s, _ = np.linalg.svd(xw, full_matrices=False)
        self.q = u[:, s > RANK_RCOND * s[0]] if s.size and s[0] > 0 else u[:, :0]
        self.zs = b.z * np.asarray(theta[: b.z.shape[2]], float)[None, None, :]
        self.yw = np.einsum("vij,vj->vi", self.w, b.y).reshape(-1)

    def __call__(self, ew: np.ndarray) -> np.ndarray:
        b = self.b
        rw = ew - (ew @ self.q) @ self.q.T
        rw = rw.reshape(*rw.shape[:-1], *b.y.shape)
        r = np.einsum("vij,...vj->...vi", self.chol, rw)
        u = np.einsum("vnq,...vn->...vq", self.zs, np.einsum("vji,...vj->...vi", self.w, rw))
        r = r - np.einsum("vnq,...vq->...vn", self.zs, u)  # V⁻¹ = WᵀW, L·rw = r
        c = b.channels
        out = np.zeros((*r.shape[:-2], self.g_n, c))
        for j in range(b.groups.shape[1]):
            g = b.groups[:, j]
            ok = g >= 0
            out[..., g[ok], :] = r[..., ok, j * c:(j + 1) * c]
        return out


def neighbour_pairs(pos_mm: np.ndarray, visit: np.ndarray, lags: Sequence[float] = LAGS_MM
                    ) -> list[tuple[int, float, np.ndarray, np.ndarray]]:
    """(axis, lag, i, j): the pairs of groups from different visits within ``lag`` of each
    other along each axis (at least ``MIN_PAIRS``)."""
    iu, ju = np.triu_indices(len(visit), 1)
    other = visit[iu] != visit[ju]
    out = []
    for a in range(3):
        d = np.abs(pos_mm[iu, a] - pos_mm[ju, a])
        for h in lags:
            m = other & (d <= h)
            if m.sum() >= MIN_PAIRS:
                out.append((a, float(h), iu[m], ju[m]))
    return out


def _pair_stats(allr: np.ndarray, pairs: list, chans: list[int]
                ) -> tuple[list[tuple], list[np.ndarray]]:
    """Near-pair correlation per (axis, lag, channel): mean product over mean square."""
    den = np.maximum(np.mean(allr**2, axis=1), 1e-300)  # (draws, c)
    keys, stats = [], []
    for a, h, i, j in pairs:
        for k in chans:
            keys.append(("pairs", a, h, k))
            stats.append(np.einsum("bp,bp->b", allr[:, i, k], allr[:, j, k]) / len(i)
                         / den[:, k])
    return keys, stats


def _scan_stats(allr: np.ndarray, pos_mm: np.ndarray, visit: np.ndarray, chans: list[int]
                ) -> tuple[list[tuple], list[np.ndarray]]:
    """Per (shape family, axis, channel): the largest share of the channel's sum of squares
    one cyclic (period scanned) or local (centre and width scanned) shape takes between
    visits (``structure_shape.cross_visit``)."""
    z = allr[:, :, chans]
    tot = np.maximum(np.sum(z**2, axis=1), 1e-300)  # (draws, c')
    keys, stats = [], []
    for a in range(3):
        for family, (phi, k) in scan_bases(pos_mm[:, a]).items():
            proj = cross_visit(z, phi, visit)
            if k == 2:
                proj = proj[..., 0::2] + proj[..., 1::2]
            best = proj.max(axis=2) / tot
            for n, ch in enumerate(chans):
                keys.append((family, a, None, ch))
                stats.append(best[:, n])
    return keys, stats


def test_structure(problem: Problem, groups: Groups, vs, cols: np.ndarray,
                   fixed: Sequence[str] = (), draws: int = DRAWS) -> Structure | None:
    """Is what the fixed columns ``cols`` (the twin, and the effects named in ``fixed``) leave
    a function of an axis' position? None without a visit model (``vs``) to test against."""
    if vs is None or len(groups) < MIN_GROUPS:
        return None
    pos, visit = groups.centres.xyz_mm, visit_ids(groups)
    pairs = neighbour_pairs(pos, visit)
    res = _Residuals(_blocks(problem, groups, vs, cols), vs.fit.sigma, len(groups))
    rng = np.random.default_rng(SEED)
    sim = res(rng.standard_normal((draws, res.yw.size)))
    obs_um = res(res.yw)
    sd = sim.std(axis=0)
    ok = live(problem)[:, : sd.shape[1]] & (sd > 0)
    sd = np.where(ok, sd, 1.0)
    # Winsorised at ±CLIP (Huber's ψ): one visit's gross residual — a pole chip below what
    # the outlier test names — must not pass for a local shape of the axis; a structure is
    # carried by several visits, each of which it moves by a few standard deviations
    allr = np.clip(np.concatenate([obs_um[None], sim]) / sd, -CLIP, CLIP) * ok
    chans = [k for k in range(allr.shape[2]) if ok[:, k].any()]
    # one statistic per axis and observation channel (an error along an axis reaches the
    # channels differently: a pitch error's local slope moves the fitted radius, hence the
    # centre along the spindle, more than the centre along the axis itself), per neighbour
    # lag and per shape family
    keys, stats = _pair_stats(allr, pairs, chans)
    k2, s2 = _scan_stats(allr, pos, visit, chans)
    keys, stats = keys + k2, np.array(stats + s2)
    mu, spread = stats[:, 1:].mean(axis=1), stats[:, 1:].std(axis=1)
    z = (stats - mu[:, None]) / np.where(spread > 0, spread, 1.0)[:, None]
    t_sim = z[:, 1:].max(axis=0)
    p = float((1 + np.sum(t_sim >= z[:, 0].max())) / (draws + 1))
    axes_p, axes_z = {}, {}
    for a in range(3):
        k = [n for n, key in enumerate(keys) if key[1] == a]
        za = float(z[k, 0].max())
        axes_z[AXES[a]] = za
        axes_p[AXES[a]] = float((1 + np.sum(t_sim >= za)) / (draws + 1))
    _, best_a, best_h, _ = keys[int(np.argmax(z[:, 0]))]
    shape, others = None, {}
    if p < ALPHA:
        r_um = allr[0] * sd  # the observed residual, winsorised
        shape = locate(pos[:, best_a], r_um, sd, ok, visit)
        others = {a: locate(pos[:, AXES.index(a)], r_um, sd, ok, visit)
                  for a, pa in axes_p.items() if pa < ALPHA and a != AXES[best_a]}
    return Structure(p, axes_p, axes_z, AXES[best_a], best_h, shape, tuple(fixed), draws,
                     others)
