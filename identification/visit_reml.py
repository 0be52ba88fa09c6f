"""The visit blocks' REML criterion: value, gradient and Hessian in the variances, and its minimum.

−2ℓ_R(φ) = log det V + log det XᵀV⁻¹X + yᵀPy (Patterson & Thompson 1971), V = V₀ + Σ_k φ_k V_k
linear in the variances φ = θ² (``visit_blocks.covariance``). Its derivatives (Harville 1977
eq. 4.4; Searle, Casella & McCulloch 1992 §6.6) with P = V⁻¹ − V⁻¹X(XᵀV⁻¹X)⁻¹XᵀV⁻¹:

    ∂/∂φ_k    = tr(P V_k) − yᵀP V_k P y
    ∂²/∂φ_k∂φ_l = −tr(P V_k P V_l) + 2 yᵀP V_k P V_l P y

(the profile (ML) criterion drops log det XᵀV⁻¹X and takes V⁻¹ for P in the traces). With the
exact Hessian, Newton's method with the bounds φ ≥ 0 held as an active set reaches the optimum
in a handful of steps (quadratically), where a quasi-Newton method needs dozens of gradients;
and it needs no optimiser library, so an analysis never imports scipy for it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from identification.visit_blocks import EIG_RCOND, VisitBlocks, covariance, fixed_basis


@dataclass(frozen=True)
class Terms:
    """−2ℓ at one θ and, as asked, its gradient and Hessians by the variances φ = θ²."""

    nll: float
    grad: np.ndarray | None = None
    hess: np.ndarray | None = None  # observed
    fisher: np.ndarray | None = None  # expected



def reml_terms(b: VisitBlocks, theta: np.ndarray, t: np.ndarray, restricted: bool = True,
               order: int = 0) -> Terms:
    """−2ℓ at θ for the fixed basis ``t`` (``visit_blocks.fixed_basis``); with ``order`` 1
    also its gradient by the variances φ = θ² (index σ² per z column, then s_x², s_y², s_z²),
    with 2 also its Hessian by φ and the expected one, tr(P V_k P V_l) (tr(V⁻¹V_kV⁻¹V_l) for
    the profile: Fisher's information × 2, positive definite, what Fisher scoring steps with
    where −2ℓ is not convex)."""
    theta = np.asarray(theta, float)
    chol = np.linalg.cholesky(covariance(b, theta))
    logdet = 2.0 * float(np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2))))
    n = chol.shape[1]
    linv = np.linalg.solve(chol, np.broadcast_to(np.eye(n), chol.shape))  # (V, n, n) L⁻¹
    xw_v = linv @ (b.x @ t)  # (V, n, r) L⁻¹X̃
    yw_v = (linv @ b.y[..., None])[..., 0]  # (V, n) L⁻¹y
    xw = xw_v.reshape(-1, t.shape[1])
    yw = yw_v.reshape(-1)
    w, vec = np.linalg.eigh(xw.T @ xw)
    w = np.maximum(w, EIG_RCOND * max(float(w[-1]), 1e-300))
    xty = xw.T @ yw
    proj = vec.T @ xty
    rss = float(yw @ yw - np.sum(proj**2 / w))
    nll = logdet + (float(np.sum(np.log(w))) if restricted else 0.0) + rss
    if order == 0:
        return Terms(nll)
    z, d = b.z, b.centre  # V_k: z_k z_kᵀ (index), diag(d_c) (centre axis c) per visit
    m_inv = (vec / w) @ vec.T  # (XᵀV⁻¹X)⁻¹ in the fixed basis
    lt = np.swapaxes(linv, 1, 2)
    py = (lt @ (yw_v - xw_v @ (m_inv @ xty))[..., None])[..., 0]  # (V, n) P y
    a = lt @ xw_v  # (V, n, r) A = V⁻¹X̃
    bv = lt @ linv  # (V, n, n) B = V⁻¹
    cv = (a @ m_inv) @ np.swapaxes(a, 1, 2)  # C: diagonal blocks of A M⁻¹ Aᵀ (P = B − C)
    bz, cz = bv @ z, cv @ z  # (V, n, q)
    q = z.shape[2]
    az = np.swapaxes(z, 1, 2) @ a  # (V, q, r) z_kᵀA per visit
    pz = bz - cz if restricted else bz
    pdiag = np.einsum("vii->vi", bv) - (np.einsum("vii->vi", cv) if restricted else 0.0)
    zpy = np.einsum("vnk,vn->vk", z, py)
    grad = np.concatenate([np.einsum("vnk,vnk->k", z, pz) - np.sum(zpy**2, axis=0),
                           np.einsum("vnc,vn->c", d, pdiag - py**2)])
    if order == 1:
        return Terms(nll, grad)
    zbz, zcz = np.swapaxes(z, 1, 2) @ bz, np.swapaxes(z, 1, 2) @ cz  # (V, q, q)
    d2 = d.reshape(-1, 3)
    # Σ_v tr(B V_k B V_l): (z_kᵀBz_l)², d_cᵀ(B∘B)d_e, Σ d_c (Bz_k)²
    tb = _square_blocks(np.einsum("vkl,vkl->kl", zbz, zbz), (bz**2).reshape(-1, q).T @ d2,
                        d2.T @ ((bv * bv) @ d).reshape(-1, 3))
    # Σ_v tr(B V_k C V_l) (symmetric): (z_lᵀBz_k)(z_kᵀCz_l), Σ d_c (Bz_k)(Cz_k), d_cᵀ(B∘C)d_e
    cross = _square_blocks(np.einsum("vkl,vkl->kl", zbz, zcz), (bz * cz).reshape(-1, q).T @ d2,
                           d2.T @ ((bv * cv) @ d).reshape(-1, 3))
    ar = a.reshape(-1, a.shape[2])
    s = np.stack([az[:, k].T @ az[:, k] for k in range(q)]
                 + [(ar * d2[:, c, None]).T @ ar for c in range(3)])  # AᵀV_kA
    r_k = m_inv[None] @ s
    tr_p = tb - 2.0 * cross + np.einsum("krs,lsr->kl", r_k, r_k)  # tr(P V_k P V_l)
    u = np.concatenate([np.moveaxis(z * zpy[:, None, :], 2, 0),
                        np.moveaxis(d * py[..., None], 2, 0)])  # (m, V, n) V_k P y
    u2 = np.moveaxis(u, 0, 2).reshape(-1, len(u))  # (V n, m)
    bu = (bv @ np.moveaxis(u, 0, 2)).reshape(-1, len(u))
    au = ar.T @ u2  # (r, m)
    quad = u2.T @ bu - au.T @ m_inv @ au  # u_kᵀ P u_l
    expected = tr_p if restricted else tb  # tr(B V_k B V_l): the profile's own
    return Terms(nll, grad, 2.0 * quad - expected, expected)


def _square_blocks(ii: np.ndarray, ic: np.ndarray, cc: np.ndarray) -> np.ndarray:
    """The (q + 3)² symmetric matrix from its index-index, index-centre and centre blocks."""
    return np.block([[ii, ic], [ic.T, cc]])


STEP_RTOL = 1e-11  # Newton stops once no variance would move by more than this, relative
STEP_ATOL = 1e-14  # µrad² / µm²: the same near a variance of zero
F_RTOL_ROUNDING = 1e-18  # a predicted fall of −2ℓ below its rounding: at the minimum
F_RTOL_NOISE = 1e-10  # a full step that fails with a predicted fall this small: no halving


def newton_bounded(fun: Callable[[np.ndarray, int], Terms], x0: np.ndarray, upper: float,
                   max_iter: int = 200) -> tuple[np.ndarray, float, int]:
    """(x, f, evaluations): a local minimum of f on 0 ≤ x ≤ ``upper``. ``fun(x, order)``
    returns its ``Terms``. A bound whose gradient pushes outwards is held (the active set);
    the step is Newton's where the free Hessian is positive definite, Fisher scoring's
    elsewhere (far from the optimum −2ℓ is concave in a variance, and a Newton step with the
    Hessian's sign turned would throw the variance to its bound), projected onto the bounds
    and halved until f falls (Armijo)."""
    x = np.clip(np.asarray(x0, float), 0.0, upper)
    cur = fun(x, 2)
    evals = 1
    for _ in range(max_iter):
        g = cur.grad
        free = ~(((x <= 0.0) & (g >= 0.0)) | ((x >= upper) & (g <= 0.0)))
        d = _direction(cur, free)
        out = (x <= 0.0) & (d < 0.0) | (x >= upper) & (d > 0.0)
        while out.any() and (free & ~out).any():  # a bound the step would cross is held too
            free &= ~out
            d = _direction(cur, free)
            out = (x <= 0.0) & (d < 0.0) | (x >= upper) & (d > 0.0)
        scale = max(1.0, abs(cur.nll))
        decrement = -float(g @ d)  # ≈ 2 (f − f_min) near the minimum
        if (not free.any() or np.all(np.abs(d) <= STEP_RTOL * x + STEP_ATOL)
                or decrement <= F_RTOL_ROUNDING * scale):
            break
        step, nxt = 1.0, None
        while step > 1e-12:
            xn = np.clip(x + step * d, 0.0, upper)
            if np.array_equal(xn, x):
                break
            trial = fun(xn, 2 if step == 1.0 else 0)
            evals += 1
            if np.isfinite(trial.nll) and trial.nll <= cur.nll + 1e-4 * min(float(g @ (xn - x)),
                                                                            0.0):
                nxt = trial
                break
            if decrement <= F_RTOL_NOISE * scale:
                break  # a step this small fails on −2ℓ's rounding: there is nothing left
            step *= 0.5
        if nxt is None:
            break  # f cannot fall further at double precision: the minimum
        if nxt.grad is None:
            nxt = fun(xn, 2)
            evals += 1
        x, cur = xn, nxt
    return x, cur.nll, evals


def _direction(t: Terms, free: np.ndarray) -> np.ndarray:
    """Newton's step on the free coordinates (0 on the held ones), Fisher scoring's where the
    free Hessian is not positive definite."""
    g, d = t.grad[free], np.zeros_like(t.grad)
    h = t.hess[np.ix_(free, free)]
    try:
        np.linalg.cholesky(h)  # positive definite: Newton
    except np.linalg.LinAlgError:
        lam, vec = np.linalg.eigh(t.fisher[np.ix_(free, free)])
        lam = np.maximum(lam, 1e-12 * max(float(lam.max()), 1e-300))
        d[free] = -vec @ ((vec.T @ g) / lam)
        return d
    d[free] = -np.linalg.solve(h, g)
    return d


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
    return reml_terms(b, theta, fixed_basis(b.x, rank), restricted).nll


def restricted_nll_grad(b: VisitBlocks, theta: np.ndarray, rank: int | None = None,
                        restricted: bool = True) -> tuple[float, np.ndarray]:
    """``restricted_nll`` and its gradient by θ (``reml_terms``' by φ = θ², × 2θ)."""
    theta = np.asarray(theta, float)
    terms = reml_terms(b, theta, fixed_basis(b.x, rank), restricted, order=1)
    return terms.nll, terms.grad * 2.0 * theta
