"""Per-visit scatter (issue 21) by REML: rotary index errors and centre scatter per ball visit.

Every indexation of B/C stops a few µrad from where it stopped last time (rotary positioning
repeatability, clamping): all balls of one visit move together, along the visit's
d(centre)/d(B) and d(centre)/d(C). On top of the sphere fit's own covariance (trigger noise)
each ball visit may scatter on its own (thesis §3.4: the measured centre repeatability,
0.66 / 0.98 / 0.44 µm, exceeds what the trigger noise explains). The observations of one visit
then have the covariance

    V_v = blockdiag_g(R_g + diag(s_x², s_y², s_z², 0)) + Z_v diag(σ_B², σ_C²) Z_vᵀ

(R_g: the sphere fit's covariance of group g; Z_v: the index columns of the visit's groups),
blocks independent between visits. The components θ = (σ_B, σ_C, s_x, s_y, s_z) are estimated
by restricted maximum likelihood (Patterson & Thompson; the fixed effects — setup, links,
selected effects — integrated out, so their dof are not taken from the scatter): repeats and
revisits inform them directly, and without repeats the pattern across the balls of one visit
tells a rigid index error from independent centre scatter. The same blocks give the
generalised-least-squares whitening the gap diagnosis and the link uncertainties use.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

EIG_RCOND = 1e-12  # relative eigenvalue cut-off of XᵀV⁻¹X (unobservable fixed directions)
LR_ALPHA = 0.01  # a component is "detected" when its boundary LR test is below this level
MAX_SIGMA = 1e4  # µrad / µm: an upper bound for the optimiser only
ZERO = 1e-2  # µrad / µm: a component this small is none (the optimiser's floor is 1e-3)
# L-BFGS-B with the analytic gradient runs to the optimum, not to a plateau: −2ℓ (hundreds)
# to a relative change of 1e-13 and a projected gradient below 1e-8 per µrad / µm, so that the
# components, and every u that carries them, are the same on every CPU and BLAS kernel to
# ~1e-9 (a stop at 1e-7 of −2ℓ left them 2e-3 apart between kernels)
FTOL = 1e-13
GTOL = 1e-8
MAX_ITER = 500
# A variance floor on every observation (µm², (0.1 nm)²): a noise-free run's sphere fits carry a
# covariance of ~0, and with every component at its bound V would be singular (its whitening
# overflowing to NaN); far below any centre's real repeatability, it changes nothing measured.
FLOOR_UM2 = 1e-8


@dataclass
class VisitBlocks:
    """Observations arranged by visit: (V, n) slots of n = K groups × c channels, padded.

    ``y`` (V, n), ``x`` (V, n, P) fixed-effect columns, ``r0`` (V, n, n) the covariance known
    without the components (pads: identity), ``z`` (V, n, q) index columns per µrad,
    ``centre`` (V, n, 3) selector of each slot's centre axis (1 where slot is channel x/y/z of
    a real group), ``groups`` (V, K) group index per slot group (−1: pad)."""

    y: np.ndarray
    x: np.ndarray
    r0: np.ndarray
    z: np.ndarray
    centre: np.ndarray
    groups: np.ndarray
    channels: int


def arrange(y: np.ndarray, x: np.ndarray, r0: np.ndarray, z: np.ndarray, visit: np.ndarray,
            live: np.ndarray | None = None) -> VisitBlocks:
    """Blocks from per-group arrays: ``y`` (G, c), ``x`` (G, c, P), ``r0`` (G, c, c),
    ``z`` (G, c, q), ``visit`` (G,) ids, ``live`` (G, c) observations that exist (a dead
    channel gets unit variance and zero data: it adds nothing to the likelihood)."""
    g_n, c = y.shape
    live = np.ones((g_n, c), bool) if live is None else np.asarray(live, bool)
    ids, inv = np.unique(visit, return_inverse=True)
    k = int(np.bincount(inv).max())
    groups = np.full((len(ids), k), -1)
    slot = np.zeros(len(ids), int)
    for g, v in enumerate(inv):
        groups[v, slot[v]] = g
        slot[v] += 1
    n = k * c
    p, q = x.shape[2], z.shape[2]
    yb = np.zeros((len(ids), n))
    xb = np.zeros((len(ids), n, p))
    zb = np.zeros((len(ids), n, q))
    rb = np.broadcast_to(np.eye(n), (len(ids), n, n)).copy()
    cb = np.zeros((len(ids), n, 3))
    lv = live[..., None]
    r_live = np.where(live[:, :, None] & live[:, None, :], r0, 0.0)
    r_live[:, np.arange(c), np.arange(c)] = np.where(live, np.diagonal(r0, axis1=1, axis2=2), 1)
    for j in range(k):
        g = groups[:, j]
        ok = g >= 0
        s = slice(j * c, (j + 1) * c)
        yb[ok, s] = np.where(live[g[ok]], y[g[ok]], 0.0)
        xb[ok, s] = np.where(lv[g[ok]], x[g[ok]], 0.0)
        zb[ok, s] = np.where(lv[g[ok]], z[g[ok]], 0.0)
        rb[ok, s, s] = r_live[g[ok]]
        for a in range(min(3, c)):
            cb[ok, j * c + a, a] = live[g[ok], a]
    return VisitBlocks(yb, xb, rb, zb, cb, groups, c)


def covariance(b: VisitBlocks, theta: np.ndarray) -> np.ndarray:
    """(V, n, n) the visits' covariances for components θ = (σ index per z column …,
    s_x, s_y, s_z) in µrad and µm."""
    q = b.z.shape[2]
    idx, cen = np.asarray(theta[:q], float), np.asarray(theta[q:], float)
    zs = b.z * idx[None, None, :]
    v = b.r0 + zs @ np.swapaxes(zs, 1, 2)
    d = np.einsum("vna,a->vn", b.centre, cen**2) + FLOOR_UM2
    v[:, np.arange(v.shape[1]), np.arange(v.shape[1])] += d
    return v


def fixed_basis(x: np.ndarray, rank: int | None = None) -> np.ndarray:
    """(P, r) a basis of the fixed columns' span that does not depend on θ: the ``rank``
    leading eigenvectors of the unwhitened, column-normalised XᵀX (all above ``EIG_RCOND``
    when None), scaled so that X·T is orthonormal."""
    xr = x.reshape(-1, x.shape[-1])
    norms = np.linalg.norm(xr, axis=0)
    norms[norms == 0] = 1.0
    w, vec = np.linalg.eigh((xr / norms).T @ (xr / norms))
    keep = np.argsort(w)[::-1][: rank if rank is not None else int(np.sum(w > EIG_RCOND * w[-1]))]
    return vec[:, keep] / norms[:, None] / np.sqrt(w[keep])


def restricted_nll(b: VisitBlocks, theta: np.ndarray, rank: int | None = None,
                   restricted: bool = True) -> float:
    """−2 × the restricted log-likelihood (constants dropped) at θ; ``rank`` the fixed
    columns' rank (their near-null directions are integrated out of neither term). With
    ``restricted`` False: −2 × the profile (ML) log-likelihood, the one that compares models
    with different fixed effects (a likelihood-ratio test of a candidate effect).

    log det(XᵀV⁻¹X) is taken in one basis of the fixed columns for every θ (``fixed_basis``):
    normalising the whitened columns instead drops 2 Σ log‖V^(-1/2) x_j‖, a term that falls
    as σ grows, and biased the components low — most the index component of B, whose few
    angles make the B-dependent link columns look like its index columns (σ̂_B/σ 0.95 on
    synthetic data of the shift plan, N = 200; 0.99 with the fixed basis)."""
    return _nll(b, theta, fixed_basis(b.x, rank), restricted, gradient=False)[0]


def restricted_nll_grad(b: VisitBlocks, theta: np.ndarray, rank: int | None = None,
                        restricted: bool = True) -> tuple[float, np.ndarray]:
    """``restricted_nll`` and its gradient by θ (analytic, Harville 1977 eq. 4.4 / Searle,
    Casella & McCulloch 1992 §6.6): with V_k = ∂V/∂θ_k²,
    ∂(−2ℓ_R)/∂θ_k² = tr(V⁻¹V_k) − tr((XᵀV⁻¹X)⁻¹XᵀV⁻¹V_kV⁻¹X) − yᵀPV_kPy
    (the ML form drops the middle term), then × 2θ_k."""
    return _nll(b, theta, fixed_basis(b.x, rank), restricted, gradient=True)


def _nll(b: VisitBlocks, theta: np.ndarray, t: np.ndarray, restricted: bool, gradient: bool
         ) -> tuple[float, np.ndarray]:
    theta = np.asarray(theta, float)
    chol = np.linalg.cholesky(covariance(b, theta))
    logdet = 2.0 * float(np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2))))
    xw_v = np.linalg.solve(chol, b.x @ t)  # (V, n, r) L⁻¹X̃
    yw_v = np.linalg.solve(chol, b.y[..., None])[..., 0]  # (V, n) L⁻¹y
    xw = xw_v.reshape(-1, t.shape[1])
    yw = yw_v.reshape(-1)
    w, vec = np.linalg.eigh(xw.T @ xw)
    w = np.maximum(w, EIG_RCOND * max(float(w[-1]), 1e-300))
    proj = vec.T @ (xw.T @ yw)
    rss = float(yw @ yw - np.sum(proj**2 / w))
    nll = logdet + (float(np.sum(np.log(w))) if restricted else 0.0) + rss
    if not gradient:
        return nll, np.zeros(0)
    m_inv = (vec / w) @ vec.T  # (XᵀV⁻¹X)⁻¹ in the fixed basis
    beta = m_inv @ (xw.T @ yw)
    lt = np.swapaxes(chol, 1, 2)
    py = np.linalg.solve(lt, (yw_v - xw_v @ beta)[..., None])[..., 0]  # (V, n) P y
    q = b.z.shape[2]
    grad = np.zeros(len(theta))
    if q:
        lz = np.linalg.solve(chol, b.z)  # (V, n, q) L⁻¹z
        wz = np.einsum("vnr,vna->var", xw_v, lz)  # X̃ᵀV⁻¹z per visit
        t1 = np.einsum("vna,vna->a", lz, lz)
        t2 = np.einsum("var,rs,vas->a", wz, m_inv, wz)
        t3 = np.einsum("vn,vna->va", py, b.z) ** 2
        grad[:q] = t1 - (t2 if restricted else 0.0) - t3.sum(axis=0)
    n = chol.shape[1]
    linv = np.linalg.solve(chol, np.broadcast_to(np.eye(n), chol.shape))
    vinv_diag = np.einsum("vin,vin->vn", linv, linv)  # diag V⁻¹
    a = np.linalg.solve(lt, xw_v)  # (V, n, r) V⁻¹X̃
    amd = np.einsum("vnr,rs,vns->vn", a, m_inv, a)
    for c in range(len(theta) - q):
        d = b.centre[:, :, c]
        grad[q + c] = float(np.sum(d * (vinv_diag - (amd if restricted else 0.0) - py**2)))
    return nll, grad * 2.0 * theta


@dataclass
class ScatterFit:
    """The estimated components (µrad, µm) with standard uncertainties and their tests."""

    names: tuple[str, ...]
    sigma: np.ndarray
    std: np.ndarray
    p_value: np.ndarray  # boundary LR test σ = 0 (½χ²₁ mixture)
    fixed: np.ndarray  # stated, not estimated
    n_visits: int
    nll: float
    # (m, 2) 95 % likelihood interval of each estimated component (NaN: stated, or not
    # computed): where −2ℓ, the other components at their estimates, rises by χ²₁(95 %)
    ci95: np.ndarray | None = None

    def value(self, name: str) -> float:
        return float(self.sigma[self.names.index(name)])


def estimate_components(b: VisitBlocks, names: Sequence[str], start: Sequence[float],
                        fixed: dict[int, float] | None = None,
                        test: bool | Sequence[int] = True,
                        restricted: bool = True) -> ScatterFit:
    """REML estimate of the components (``fixed``: index → stated value, not estimated).
    Each free component gets its boundary likelihood-ratio p-value (refit with it at zero)
    when ``test`` (True, or the indices to test), and a standard uncertainty from the
    curvature of −2ℓ (σ ≥ 0)."""
    fixed = dict(fixed or {})
    m = len(names)
    free = [i for i in range(m) if i not in fixed]
    basis = fixed_basis(b.x)
    rank = basis.shape[1]

    def full(t: np.ndarray, zero: int | None = None) -> np.ndarray:
        out = np.array([fixed.get(i, 0.0) for i in range(m)], float)
        out[[i for i in free if i != zero]] = t
        return out

    def solve(zero: int | None = None, x0: np.ndarray | None = None
              ) -> tuple[np.ndarray, float]:
        idx = [i for i in free if i != zero]
        if not idx:
            return np.zeros(0), restricted_nll(b, full(np.zeros(0), zero), rank, restricted)
        x0 = np.maximum([start[i] for i in idx] if x0 is None else x0[idx], 1e-3)
        from scipy import optimize  # lazy: a run without visit blocks never loads it

        def f(t: np.ndarray) -> tuple[float, np.ndarray]:
            v, g = _nll(b, full(t, zero), basis, restricted, gradient=True)
            return v, g[idx]

        res = optimize.minimize(f, x0, jac=True, method="L-BFGS-B",
                                bounds=[(0.0, MAX_SIGMA)] * len(idx),
                                options={"maxiter": MAX_ITER, "ftol": FTOL, "gtol": GTOL})
        return res.x, float(res.fun)

    # The likelihood is not convex in σ: a local optimum far out (one component taking up a
    # systematic residual) can hide a better one with that component at zero. Two starts,
    # and every boundary fit of the tests that beats the optimum restarts it from there.
    cands = [solve(), solve(x0=10.0 * np.asarray(start, float))]
    t_hat, nll = min(cands, key=lambda r: r[1])
    sigma = full(t_hat)
    for _ in range(len(free) + 1):
        p_val = np.full(m, np.nan)
        better = None
        for i in [i for i in free if test is True or (test and i in test)]:
            if sigma[i] <= ZERO:
                p_val[i] = 1.0
                continue
            t0, nll0 = solve(i, sigma)
            if nll0 < nll - 1e-3:
                better = full(t0, i)
                break
            # χ²(1) survival function: P(χ²₁ > x) = erfc(√(x/2)) (no scipy.stats import: ~1 s)
            p_val[i] = 0.5 * math.erfc(math.sqrt(max(nll0 - nll, 0.0) / 2.0))
        if better is None:
            break
        t_hat, nll = solve(x0=np.where(better > 0, better, 1e-3))
        sigma = full(t_hat)
    std = np.full(m, np.nan)
    for i in free:
        h = max(1e-3, 1e-2 * sigma[i])
        if sigma[i] > h:
            f = [restricted_nll(b, sigma + dv * h * np.eye(m)[i], rank, restricted)
                 for dv in (-1, 0, 1)]
            curv = (f[0] - 2 * f[1] + f[2]) / h**2  # d²(−2ℓ)/dσ²: var σ ≈ 2 / curv
            std[i] = np.sqrt(2.0 / curv) if curv > 0 else np.inf
    ci = np.full((m, 2), np.nan)
    if test is not False:
        for i in free:
            ci[i] = _interval(lambda v, i=i: restricted_nll(
                b, np.where(np.arange(m) == i, v, sigma), rank, restricted) - nll, sigma[i])
    return ScatterFit(tuple(names), sigma, std, p_val,
                      np.array([i in fixed for i in range(m)]), len(b.groups), nll, ci)


CHI2_1_95 = 3.841  # χ²₁ 95 % quantile: the likelihood interval's rise of −2ℓ


def _interval(rise: Callable[[float], float], est: float) -> tuple[float, float]:
    """The 95 % likelihood interval of one σ: where ``rise`` (−2ℓ above its minimum) reaches
    χ²₁(95 %) either side of ``est`` (0 when it stays below at σ = 0). With a dozen visits
    σ̂ is skewed (a scaled χ with ~ν dof): the curvature's symmetric ± 2u at a low σ̂ is too
    short upwards; the likelihood interval is not (issue 21, bench_scatter: 2u held the true
    B repeatability in ~80-88 % of the null runs)."""
    from scipy.optimize import brentq  # lazy, as in estimate_components

    def f(v: float) -> float:
        return rise(v) - CHI2_1_95

    lo = 0.0
    if est > ZERO and f(0.0) > 0:
        lo = brentq(f, 0.0, est, xtol=1e-3 * max(est, ZERO))
    hi, top = est, max(est, 1.0)
    while hi < MAX_SIGMA:
        hi = min(2.0 * max(hi, top / 2), MAX_SIGMA)
        if f(hi) > 0:
            break
    else:
        return lo, math.inf
    hi = brentq(f, est, hi, xtol=1e-3 * max(est, ZERO))
    return lo, hi


def whiteners(b: VisitBlocks, theta: np.ndarray) -> np.ndarray:
    """(V, n, n) inverse Cholesky factors of the visits' covariances: GLS whitening."""
    chol = np.linalg.cholesky(covariance(b, theta))
    eye = np.broadcast_to(np.eye(chol.shape[1]), chol.shape)
    return np.linalg.solve(chol, eye)


def effective_dof(b: VisitBlocks, theta: np.ndarray, fit: ScatterFit, base_dof: float
                  ) -> float:
    """Welch–Satterthwaite dof of the floor's mean variance: the trigger-noise part with
    ``base_dof``, each estimated component with 2 (σ/u(σ))² (its relative uncertainty)."""
    q = b.z.shape[2]
    parts = [float(np.sum(np.diagonal(b.r0, axis1=1, axis2=2)))]
    dofs = [max(base_dof, 1.0)]
    for i in range(len(theta)):
        if i < q:
            share = float(np.sum(b.z[:, :, i] ** 2)) * theta[i] ** 2
        else:
            share = float(np.sum(b.centre[:, :, i - q])) * theta[i] ** 2
        if share <= 0:
            continue
        rel = fit.std[i] / theta[i] if np.isfinite(fit.std[i]) and theta[i] > 0 else np.inf
        if fit.fixed[i]:
            dof = 1e6
        else:
            dof = max(0.5 / rel**2, 1.0) if np.isfinite(rel) else max(fit.n_visits - 1, 1)
        parts.append(share)
        dofs.append(dof)
    tot = sum(parts)
    return float(tot**2 / sum(p**2 / d for p, d in zip(parts, dofs, strict=True)))
