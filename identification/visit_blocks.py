"""Observations arranged by ball visit for the visit-scatter model: blocks, covariance, basis.

The visits' covariances V_v = blockdiag_g(R_g + diag(s²)) + Z_v diag(σ²) Z_vᵀ and the fixed
columns' θ-free basis that ``identification.visit_reml`` (the REML criterion) and
``identification.visit_scatter`` (the components' estimate) share.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

EIG_RCOND = 1e-12  # relative eigenvalue cut-off of XᵀV⁻¹X (unobservable fixed directions)
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
