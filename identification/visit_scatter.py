"""Per-visit scatter by REML: rotary index errors and centre scatter per ball visit.

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

from identification.brent import find_root
from identification.visit_blocks import (
    EIG_RCOND,
    FLOOR_UM2,
    VisitBlocks,
    arrange,
    covariance,
    fixed_basis,
)
from identification.visit_reml import (
    Terms,
    newton_bounded,
    reml_terms,
    restricted_nll,
    restricted_nll_grad,
)

__all__ = ["EIG_RCOND", "FLOOR_UM2", "LR_ALPHA", "ScatterFit", "VisitBlocks", "arrange",
           "covariance", "effective_dof", "estimate_components", "fixed_basis", "restricted_nll",
           "restricted_nll_grad", "whiteners"]

LR_ALPHA = 0.01  # a component is "detected" when its boundary LR test is below this level
MAX_SIGMA = 1e4  # µrad / µm: an upper bound for the optimiser only
ZERO = 1e-2  # µrad / µm: a component this small is none (the optimiser's floor is 1e-3)
# Newton's method on the variances with the exact Hessian (``visit_reml``) runs to the optimum,
# not to a plateau (no variance moving by 1e-11 relative), so that the components, and every u
# that carries them, are the same on every CPU and BLAS kernel to ~1e-9.

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
                        restricted: bool = True, intervals: bool = True) -> ScatterFit:
    """REML estimate of the components (``fixed``: index → stated value, not estimated).
    Each free component gets its boundary likelihood-ratio p-value (refit with it at zero)
    when ``test`` (True, or the indices to test), a standard uncertainty from the curvature
    of −2ℓ (σ ≥ 0) and, with ``intervals`` and ``test``, its 95 % likelihood interval."""
    fixed = dict(fixed or {})
    m = len(names)
    free = [i for i in range(m) if i not in fixed]
    basis = fixed_basis(b.x)

    def full(t: np.ndarray, zero: int | None = None) -> np.ndarray:
        out = np.array([fixed.get(i, 0.0) for i in range(m)], float)
        out[[i for i in free if i != zero]] = t
        return out

    def nll_at(theta: np.ndarray) -> float:
        return reml_terms(b, theta, basis, restricted).nll

    def solve(zero: int | None = None, x0: np.ndarray | None = None
              ) -> tuple[np.ndarray, float]:
        idx = [i for i in free if i != zero]
        if not idx:
            return np.zeros(0), nll_at(full(np.zeros(0), zero))
        x0 = np.maximum([start[i] for i in idx] if x0 is None else x0[idx], 1e-3)

        def terms(phi: np.ndarray, order: int) -> Terms:
            t = reml_terms(b, full(np.sqrt(phi), zero), basis, restricted, order)
            if order == 0:
                return t
            sub = np.ix_(idx, idx)
            return Terms(t.nll, t.grad[idx], t.hess[sub], t.fisher[sub])

        phi, f, _ = newton_bounded(terms, np.square(x0), MAX_SIGMA**2)
        return np.sqrt(phi), f

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
    at_sigma = None
    for i in free:
        h = max(1e-3, 1e-2 * sigma[i])
        if sigma[i] > h:
            at_sigma = nll_at(sigma) if at_sigma is None else at_sigma
            f = [nll_at(sigma - h * np.eye(m)[i]), at_sigma, nll_at(sigma + h * np.eye(m)[i])]
            curv = (f[0] - 2 * f[1] + f[2]) / h**2  # d²(−2ℓ)/dσ²: var σ ≈ 2 / curv
            std[i] = np.sqrt(2.0 / curv) if curv > 0 else np.inf
    ci = np.full((m, 2), np.nan)
    if intervals and test is not False:
        for i in free:
            ci[i] = _interval(lambda v, i=i: nll_at(np.where(np.arange(m) == i, v, sigma))
                              - nll, sigma[i])
    return ScatterFit(tuple(names), sigma, std, p_val,
                      np.array([i in fixed for i in range(m)]), len(b.groups), nll, ci)


CHI2_1_95 = 3.841  # χ²₁ 95 % quantile: the likelihood interval's rise of −2ℓ


def _interval(rise: Callable[[float], float], est: float) -> tuple[float, float]:
    """The 95 % likelihood interval of one σ: where ``rise`` (−2ℓ above its minimum) reaches
    χ²₁(95 %) either side of ``est`` (0 when it stays below at σ = 0). With a dozen visits
    σ̂ is skewed (a scaled χ with ~ν dof): the curvature's symmetric ± 2u at a low σ̂ is too
    short upwards; the likelihood interval is not (bench_scatter: 2u held the true
    B repeatability in ~80-88 % of the null runs)."""
    def f(v: float) -> float:
        return rise(v) - CHI2_1_95

    lo = 0.0
    if est > ZERO and f(0.0) > 0:
        lo = find_root(f, 0.0, est, xtol=1e-3 * max(est, ZERO))
    hi, top = est, max(est, 1.0)
    while hi < MAX_SIGMA:
        hi = min(2.0 * max(hi, top / 2), MAX_SIGMA)
        if f(hi) > 0:
            break
    else:
        return lo, math.inf
    hi = find_root(f, est, hi, xtol=1e-3 * max(est, ZERO))
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
