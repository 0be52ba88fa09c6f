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

The test, per controller axis a ∈ {X, Y, Z}, uses only what the visit model cannot produce:
pairs of ball visits from *different* indexations whose centres lie within ``h`` of each other
along a (``LAGS_MM``). Their residuals — the generalised-least-squares residuals of the twin on
every group, training and held-out together, under the run's scatter components, with each
visit's best rigid index displacement (its BLUP) removed and each observation standardised —
are uncorrelated under the visit model whatever the size of its components, and positively
correlated when the residual is a function of the axis position that varies more slowly than
``h``: the statistic, per observation channel (centre x, y, z, form residual: an error reaches
them differently), is their mean product over the mean square, a Moran's I restricted to
pairs that are neighbours along one axis (Moran 1950, Biometrika 37:17; Cliff & Ord 1981,
"Spatial Processes", ch. 1-2; the short-lag end of the semivariogram, Cressie 1993 §2.2).
Its null distribution is a Monte Carlo test under the fitted visit model (Besag & Diggle 1977,
Appl. Statist. 26:327): ``DRAWS`` residual vectors drawn from the model with the run's
components, projected off the same fixed columns and treated the same way, so the leverage of
the twin, the held-out groups and the index scatter are all in it. Each (axis, lag, channel)
statistic is standardised by its Monte Carlo mean and spread; the largest over the three axes,
the lags and the channels is the test statistic, the Monte Carlo distribution of that maximum
its reference — the single-step max-T adjustment of Westfall & Young (1993, "Resampling-Based
Multiple Testing" §2.5), which holds the family-wise level ``ALPHA`` over axes, lags and
channels and gives each axis an adjusted p-value. The draws come from a fixed seed: a log
always gives the same answer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.gap.data import Groups
from identification.gap.linear import Problem, live
from identification.gap.structure_shape import Shape, locate
from identification.visit_scatter import VisitBlocks, arrange, covariance

ALPHA = 0.01  # family-wise level over the three axes, the lags and the channels
LAGS_MM = (3.0, 6.0, 12.0, 24.0)  # neighbours along the axis: a 20 mm period needs ≤ 5 mm
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
    notes: list[str] = field(default_factory=list)

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
               "test": "Monte Carlo max-T over axes and lags of the neighbour correlation of "
                       "residuals from different visits (rigid index displacement removed)",
               "message": self.message()}
        if self.found and self.shape is not None:
            out["located"] = self.shape.as_dict(self.axis)
        return out

    def message(self) -> str:
        ps = ", ".join(f"{a} p = {p:.2g}" for a, p in self.axes_p.items())
        fixed = f" with {', '.join(self.fixed)} fixed" if self.fixed else ""
        if not self.found:
            return (f"no structure along X, Y or Z{fixed} ({ps}; α = {ALPHA:g} over the "
                    "axes): what the visits leave is not a function of an axis' position")
        where = self.shape.describe(self.axis) if self.shape is not None else ""
        return (f"structure along {self.axis}{fixed}{': ' + where if where else ''} (p = "
                f"{self.p_value:.2g} over X, Y, Z; {ps}) — neighbours along {self.axis} from "
                "different visits agree: a function of the axis position that comes back "
                "where the axis returns (a pitch error, a local defect of a guideway), not "
                "visit scatter")


def _blocks(problem: Problem, groups: Groups, vs, cols: np.ndarray) -> VisitBlocks:
    from identification.gap.scatter import visit_ids

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


def test_structure(problem: Problem, groups: Groups, vs, cols: np.ndarray,
                   fixed: Sequence[str] = (), draws: int = DRAWS) -> Structure | None:
    """Is what the fixed columns ``cols`` (the twin, and the effects named in ``fixed``) leave
    a function of an axis' position? None without a visit model (``vs``) to test against."""
    from identification.gap.scatter import visit_ids

    if vs is None:
        return None
    visit = visit_ids(groups)
    pairs = neighbour_pairs(groups.centres.xyz_mm, visit)
    if not pairs:
        return None
    res = _Residuals(_blocks(problem, groups, vs, cols), vs.fit.sigma, len(groups))
    rng = np.random.default_rng(SEED)
    sim = res(rng.standard_normal((draws, res.yw.size)))
    obs_um = res(res.yw)
    sd = sim.std(axis=0)
    ok = live(problem)[:, : sd.shape[1]] & (sd > 0)
    sd = np.where(ok, sd, 1.0)
    allr = np.concatenate([obs_um[None], sim]) / sd * ok  # (1 + draws, G, c)
    chans = [k for k in range(allr.shape[2]) if ok[:, k].any()]
    den = np.mean(allr**2, axis=1)  # (1 + draws, c)
    # one statistic per axis, lag and observation channel: an error along an axis reaches
    # the channels differently (a pitch error's local slope moves the fitted radius, hence
    # the centre along the spindle, more than the centre along the axis itself)
    keys = [(a, h, k) for a, h, _, _ in pairs for k in chans]
    stats = np.array([np.einsum("bp,bp->b", allr[:, i, k], allr[:, j, k]) / len(i)
                      / np.maximum(den[:, k], 1e-300) for _, _, i, j in pairs for k in chans])
    mu, spread = stats[:, 1:].mean(axis=1), stats[:, 1:].std(axis=1)
    z = (stats - mu[:, None]) / np.where(spread > 0, spread, 1.0)[:, None]
    t_sim = z[:, 1:].max(axis=0)
    p = float((1 + np.sum(t_sim >= z[:, 0].max())) / (draws + 1))
    axes_p, axes_z = {}, {}
    for a in range(3):
        k = [n for n, (aa, *_) in enumerate(keys) if aa == a]
        if k:
            za = float(z[k, 0].max())
            axes_z[AXES[a]] = za
            axes_p[AXES[a]] = float((1 + np.sum(t_sim >= za)) / (draws + 1))
    best_a, best_h, _ = keys[int(np.argmax(z[:, 0]))]
    shape = None
    if p < ALPHA:
        shape = locate(groups.centres.xyz_mm[:, best_a], obs_um, sd, ok)
    return Structure(p, axes_p, axes_z, AXES[best_a], best_h, shape, tuple(fixed), draws)
