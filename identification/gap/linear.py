"""Weighted linear least squares of the linearised twin (+ effects), fitted and cross-validated.

Observations are (G, 4) per ball-pose group (centre x y z and form residual, µm), whitened per
group by the inverse Cholesky factor of their noise covariance (``data.Groups``). A held-out
group is always predicted by a fit that did not see it (seed 004, Figs 5-9 and Table 2: a
fitted model is judged on independent measurements): folds of whole poses, contiguous in
time, or a separate log.
Under pure noise the whitened held-out residual has expected square n + trace(X_h (X_t'X_t)^+ X_h')
(the prediction variance of the fitted parameters), which gives the held-out floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RCOND = 1e-9  # relative singular-value cut-off on unit-norm columns
GRAM_RCOND = 1e-13  # the same on the normal equations (eigenvalues = squared singular values)
VISIBLE = 0.01  # visible: a typical-size effect moves the observations by > 1 % of the floor
CONDITION = 0.05  # keep parameter directions seen at least this well relative to the best


@dataclass
class Problem:
    y_um: np.ndarray  # (G, 4) measured − twin prediction at the linearisation point
    base: np.ndarray  # (G, 4, P) twin columns, µm per model unit
    whiten: np.ndarray  # (G, 4, 4) inverse Cholesky factors of the noise covariance
    fold: np.ndarray  # (G,) CV fold id; -1 = always training (separate hold-out mode)
    _base_u: tuple | None = None  # cached orthonormal basis of the twin's whitened columns
    # Per-visit whitening (``identification.visit_scatter``): (groups (V, K) with −1
    # pads, inverse Cholesky factors (V, 4K, 4K)); replaces ``whiten`` where set. Folds and
    # training sets are unions of whole visits, so a visit is never split by it.
    visit: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def folds(self) -> list[int]:
        return sorted(int(f) for f in np.unique(self.fold) if f >= 0)


@dataclass
class HeldOut:
    """Held-out residuals of one model over every held-out group (in fold order)."""

    index: np.ndarray  # (H,) group indices
    e_um: np.ndarray  # (H, 4)
    e_w: np.ndarray  # (H, 4) whitened
    expected: np.ndarray  # (H, 4) expected e_w² under pure noise: 1 + leverage of the fit
    n_obs: int

    @property
    def expected_ss(self) -> float:
        return float(np.sum(self.expected))

    @property
    def rms_um(self) -> float:
        return float(np.sqrt(np.mean(self.e_um[self.expected > 0] ** 2)))  # live observations

    @property
    def max_um(self) -> float:
        return float(np.max(np.abs(self.e_um)))

    @property
    def ss_w(self) -> float:
        return float(np.sum(self.e_w**2))

    @property
    def ratio(self) -> float:
        """Held-out whitened mean square over its pure-noise expectation (1 at the floor)."""
        return self.ss_w / self.expected_ss


@dataclass
class FullFit:
    beta: np.ndarray  # coefficients, column units
    cov: np.ndarray  # (k, k) covariance, a-posteriori variance factor ≥ 1 applied
    rss_w: float
    rank: int
    n_obs: int
    e_um: np.ndarray  # (G', 4) residuals on the training groups


def whitened(p: Problem, a: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """``a`` (G, 4) or (G, 4, k) whitened — per group, or per visit where ``p.visit`` is
    set — at ``rows`` (default all; with visits, ``rows`` must hold whole visits)."""
    rows = np.arange(len(p.fold)) if rows is None else rows
    if p.visit is None:
        spec = "gij,gj->gi" if a.ndim == 2 else "gij,gjk->gik"
        return np.einsum(spec, p.whiten[rows], a[rows])
    groups, w = p.visit
    tail = a.shape[2:]
    padded = np.concatenate([a, np.zeros((1, *a.shape[1:]))])[groups]  # (V, K, 4, …)
    flat = padded.reshape(len(groups), -1, *tail)
    out = np.einsum("vij,vj...->vi...", w, flat).reshape(padded.shape)
    full = np.zeros_like(a, dtype=float)
    ok = groups >= 0
    full[groups[ok]] = out[ok]
    full *= live(p)[(...,) + (None,) * len(tail)]
    return full[rows]


def _w(p: Problem, cols: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = whitened(p, cols, rows).reshape(-1, cols.shape[2])
    y = whitened(p, p.y_um, rows).reshape(-1)
    return x, y


def columns(p: Problem, extra: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([p.base, *extra], axis=2) if extra else p.base


def _svd(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    norms = np.linalg.norm(x, axis=0)
    norms[norms == 0] = 1.0
    u, s, vt = np.linalg.svd(x / norms, full_matrices=False)
    r = int(np.sum(s > RCOND * s[0])) if s.size and s[0] > 0 else 0
    return u[:, :r], s[:r], vt[:r], norms, r


def _gram_solve(gram: np.ndarray, xty: np.ndarray, norms: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, int]:
    """Minimum-norm solution and pseudo-inverse from the normal equations of unit-norm
    columns (k × k: a few hundred flops, where an SVD of the tall matrix per fold would cost
    the whole budget). Eigenvalues below ``GRAM_RCOND`` of the largest are dropped."""
    g = gram / np.outer(norms, norms)
    w, v = np.linalg.eigh(g)
    keep = w > GRAM_RCOND * w[-1]
    pinv = (v[:, keep] / w[keep]) @ v[:, keep].T
    beta = pinv @ (xty / norms) / norms
    return beta, pinv / np.outer(norms, norms), int(keep.sum())


def fit(p: Problem, cols: np.ndarray, rows: np.ndarray | None = None) -> FullFit:
    """Fit on ``rows`` (default: every training group, i.e. all with fold ≥ -1 in CV mode,
    only the fold -1 groups in separate hold-out mode)."""
    if rows is None:
        rows = np.flatnonzero(p.fold == -1) if np.any(p.fold == -1) else np.arange(len(p.fold))
    x, y = _w(p, cols, rows)
    norms = np.linalg.norm(x, axis=0)
    norms[norms == 0] = 1.0
    beta, pinv, r = _gram_solve(x.T @ x, x.T @ y, norms)
    res = y - x @ beta
    rss = float(res @ res)
    n_obs = int(live(p)[rows].sum())
    dof = max(n_obs - r, 1)
    factor = max(1.0, rss / dof)  # never claim better than the probing repeatability
    e_um = p.y_um[rows] - np.einsum("gjk,k->gj", cols[rows], beta)
    return FullFit(beta, pinv * factor, rss, r, n_obs, e_um)


def live(p: Problem) -> np.ndarray:
    """(G, 4) the observations that are observations: a zero whitener row (no form residual,
    ``data.Groups.channels`` 3) is none and counts neither in expectations nor in dof."""
    return np.any(p.whiten != 0.0, axis=2)


def held_out(p: Problem, cols: np.ndarray) -> HeldOut:
    """Predict every held-out group from a fit without it (all folds). The training normal
    equations of a fold are those of all groups minus the fold's own."""
    everything = np.arange(len(p.fold))
    x, y = _w(p, cols, everything)
    gram_all, xty_all = x.T @ x, x.T @ y
    norms = np.linalg.norm(x, axis=0)
    norms[norms == 0] = 1.0
    row_group = np.repeat(everything, 4)
    obs = live(p)
    idx, e_um, e_w, expd = [], [], [], []
    for f in p.folds:
        te = np.flatnonzero(p.fold == f)
        rows = np.isin(row_group, te)
        xf, yf = x[rows], y[rows]
        beta, pinv, _ = _gram_solve(gram_all - xf.T @ xf, xty_all - xf.T @ yf, norms)
        e = p.y_um[te] - np.einsum("gjk,k->gj", cols[te], beta)
        expd.append(obs[te] * (1.0 + np.einsum("ij,jk,ik->i", xf, pinv, xf).reshape(-1, 4)))
        idx.append(te)
        e_um.append(e)
        if p.visit is None:
            e_w.append(np.einsum("gij,gj->gi", p.whiten[te], e))
        else:
            e_all = np.zeros_like(p.y_um)
            e_all[te] = e
            e_w.append(whitened(p, e_all, te))
    ix = np.concatenate(idx)
    return HeldOut(ix, np.concatenate(e_um), np.concatenate(e_w), np.concatenate(expd),
                   int(obs[ix].sum()))


def projected(p: Problem, base_cols: np.ndarray, extra: np.ndarray,
              typical: np.ndarray | None = None) -> tuple[np.ndarray, int, np.ndarray]:
    """What the probing pattern can see of an effect once the twin's setup and link errors
    have absorbed what they can (all groups, whitened).

    Returns the twin-orthogonal columns, the visible rank and a basis (m, r) of parameter
    directions: an effect of ``typical`` size (per parameter, its units) changes the
    observations along each kept direction by more than ``VISIBLE`` of the noise floor (RMS
    over all observations) and by more than ``CONDITION`` of its best-seen direction. The
    rest is truncated (truncated-SVD regression): on a limited range of angles, for instance,
    a slope and first harmonics are nearly collinear and would only amplify noise.
    """
    rows = np.arange(len(p.fold))
    key = id(base_cols)
    if p._base_u is None or p._base_u[0] != key:
        xb, _ = _w(p, base_cols, rows)
        p._base_u = (key, _svd(xb)[0])
    u = p._base_u[1]
    xe, _ = _w(p, extra, rows)
    xe_perp = xe - u @ (u.T @ xe)
    m = xe.shape[1]
    if m == 0:
        return xe_perp, 0, np.zeros((0, 0))
    t = np.ones(m) if typical is None else np.asarray(typical, float)
    _, s, vt = np.linalg.svd(xe_perp * t, full_matrices=False)
    s = s / np.sqrt(xe.shape[0])
    keep = (s > VISIBLE) & (s > CONDITION * s[0])
    return xe_perp, int(keep.sum()), t[:, None] * vt[keep].T
