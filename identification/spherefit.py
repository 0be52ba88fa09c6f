"""Batched sphere-centre fit of the five stylus-centre points per (pose, ball) (METHOD.md §1).

The touches latch the stylus-centre position, so the points lie on a sphere of radius
ball radius + stylus radius around the ball centre. Free radius (default): an algebraic
(Kåsa) solve gives the start, then Gauss-Newton on the geometric distances |p - c| - R;
fixed radius: Gauss-Newton on the centre only. Everything is vectorised over the groups.
Health figures per group (thesis §3.4: a damaged or dirty ball shows up here first):
radius deviation = fitted − nominal radius (µm) and form residual RMS (µm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

_GN_ITER = 10
_GN_TOL_MM = 1e-12


class SphereFitError(ValueError):
    """The points of a group cannot define a sphere (too few, degenerate, not finite).

    ``groups``: indices of the offending groups (empty when the whole input is wrong), so a
    caller can name them (ball, pose); ``reason``: the failure without the indices."""

    def __init__(self, reason: str, groups: Sequence[int] | np.ndarray = ()) -> None:
        self.reason = reason
        self.groups = [int(g) for g in groups]
        super().__init__(reason + (f" in groups {self.groups[:10]}" if self.groups else ""))


def _bad_groups(mask: np.ndarray) -> np.ndarray:
    return np.flatnonzero(mask.reshape(mask.shape[0], -1).any(axis=1))


@dataclass(frozen=True)
class SphereFit:
    """Per-group results, all arrays of length G (groups)."""

    centre_mm: np.ndarray  # (G, 3)
    radius_mm: np.ndarray  # (G,) fitted (= nominal in fixed-radius mode)
    radius_dev_um: np.ndarray  # (G,) fitted − nominal (0 in fixed-radius mode)
    form_rms_um: np.ndarray  # (G,) RMS of the geometric residuals |p - c| - R


def _algebraic(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|p|² = 2 c·p + (R² − |c|²): linear in (c, k); solved per group by normal equations."""
    a = np.concatenate([2.0 * points, np.ones((*points.shape[:2], 1))], axis=2)  # (G, n, 4)
    rhs = np.sum(points**2, axis=2)
    ata = a.transpose(0, 2, 1) @ a
    atb = (a.transpose(0, 2, 1) @ rhs[..., None])[..., 0]
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(ata)
    if np.any(~np.isfinite(cond) | (cond > 1e14)):
        bad = np.flatnonzero(~np.isfinite(cond) | (cond > 1e14))
        raise SphereFitError("degenerate points (identical, collinear or coplanar)", bad)
    sol = np.linalg.solve(ata, atb[..., None])[..., 0]
    c = sol[:, :3]
    r = np.sqrt(np.maximum(sol[:, 3] + np.sum(c**2, axis=1), 0.0))
    return c, r


def fit_spheres(points_mm: np.ndarray, nominal_radius_mm: np.ndarray | float,
                fixed_radius: bool = False) -> SphereFit:
    """Fit one sphere per group. ``points_mm`` (G, n, 3) with n ≥ 4 (free) or n ≥ 3 (fixed);
    ``nominal_radius_mm`` scalar or (G,) = ball radius + stylus radius."""
    pts = np.asarray(points_mm, float)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise SphereFitError(f"points must be (groups, n, 3), got {pts.shape}")
    g, n, _ = pts.shape
    need = 3 if fixed_radius else 4
    if n < need:
        raise SphereFitError(f"{n} points per group; a {'fixed' if fixed_radius else 'free'}"
                             f"-radius sphere needs at least {need}")
    r_nom = np.broadcast_to(np.asarray(nominal_radius_mm, float), (g,)).copy()
    if not np.all(np.isfinite(pts)):
        raise SphereFitError("coordinates are not finite", _bad_groups(~np.isfinite(pts)))
    # Work relative to the group mean: better conditioned normal equations. Coordinates near
    # the float range (1e308) overflow here; squared (1e155 and up) in the solves below.
    with np.errstate(all="ignore"):
        mean = pts.mean(axis=1, keepdims=True)
        p = pts - mean
        huge = ~np.isfinite(p) | ~np.isfinite(np.sum(p**2, axis=2))[..., None]
    if huge.any():
        raise SphereFitError("coordinates too large to fit", _bad_groups(huge))
    with np.errstate(all="ignore"):
        return _fit(p, mean, r_nom, fixed_radius)


def _fit(p: np.ndarray, mean: np.ndarray, r_nom: np.ndarray, fixed_radius: bool) -> SphereFit:
    """Gauss-Newton on mean-centred points (see ``fit_spheres``)."""
    g, n, _ = p.shape
    if fixed_radius and n < 4:
        c = np.zeros((g, 3))
    else:
        c, _ = _algebraic(p)
    r = r_nom.copy()
    for _ in range(_GN_ITER):
        diff = p - c[:, None, :]
        dist = np.linalg.norm(diff, axis=2)
        u = diff / np.where(dist > 0, dist, 1.0)[..., None]  # d(dist)/dc = -u
        res = dist - r[:, None]
        # (G, n, 3) fixed radius, (G, n, 4) free radius
        jac = -u if fixed_radius else np.concatenate([-u, -np.ones((g, n, 1))], axis=2)
        jtj = jac.transpose(0, 2, 1) @ jac
        jtr = (jac.transpose(0, 2, 1) @ res[..., None])[..., 0]
        try:
            step = -np.linalg.solve(jtj, jtr[..., None])[..., 0]
        except np.linalg.LinAlgError:
            cond = np.linalg.cond(jtj)
            raise SphereFitError("singular normal equations (degenerate points)",
                                 np.flatnonzero(~np.isfinite(cond) | (cond > 1e14))) from None
        c = c + step[:, :3]
        if not fixed_radius:
            r = r + step[:, 3]
        if np.max(np.abs(step)) < _GN_TOL_MM:
            break
    res = np.linalg.norm(p - c[:, None, :], axis=2) - r[:, None]
    form = np.sqrt(np.mean(res**2, axis=1)) * 1e3
    bad = ~np.isfinite(c).all(axis=1) | ~np.isfinite(r) | ~np.isfinite(form)
    if bad.any():
        raise SphereFitError("the fit did not converge to finite numbers", np.flatnonzero(bad))
    return SphereFit(c + mean[:, 0, :], r, (r - r_nom) * 1e3, form)


def centre_sensitivity(points_mm: np.ndarray, centre_mm: np.ndarray,
                       fixed_radius: bool = False) -> np.ndarray:
    """(G, n, 3, 3) ∂(fitted centre)/∂(touch point i) of the least-squares sphere fit at its
    solution (first order; Σ_i = I, a translation of every point moves the centre by it).
    A drift moving the ball while it is touched (a warm-up) reaches the centre as
    Σ_i S_i δ(t_i): along X and Y at about the equator touches' times, along Z at the pole's —
    not at the mean touch time (on the thesis shift plan under a 20 µm warm-up that difference
    biased EB0C by −0.11 u and EX0C by +0.09 u)."""
    p = np.asarray(points_mm, float)
    d = p - np.asarray(centre_mm, float)[:, None, :]
    u = d / np.linalg.norm(d, axis=2, keepdims=True)
    # residual_i = |p_i − c| − r: ∂res/∂(c, r) = [−u_i, −1], ∂res_i/∂p_i = u_iᵀ, so
    # δ(c, r) = −(JᵀJ)⁻¹Jᵀ δres and ∂c/∂p_i = −[(JᵀJ)⁻¹Jᵀ]_{c,i} u_iᵀ
    jac = -u if fixed_radius else np.concatenate([-u, -np.ones((*u.shape[:2], 1))], axis=2)
    gain = np.linalg.solve(jac.transpose(0, 2, 1) @ jac, jac.transpose(0, 2, 1))  # (G, q, n)
    return -np.einsum("gai,gib->giab", gain[:, :3, :], u)
