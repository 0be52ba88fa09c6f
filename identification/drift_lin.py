"""The drift search's linearised least squares: the chain linearised at the plain
estimate (affine in µm-size changes to < 1 nm) and the weighted solve of r ≈ J δp + D θ with
drift columns D, shared by the model search and its refit (identification/drift.py), and the
selection share: the spread of the links over the models BIC chose among."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from identification.estimate import Estimate, distance_rows
from identification.kinematics import Machine
from identification.model import Artefact, Centres, predict


class Columns(Protocol):
    """A drift model as the selection share sees it (``identification.drift.DriftModel``)."""

    axes: tuple[str, ...]

    def columns(self, t_s: np.ndarray, touch: Any = None) -> np.ndarray: ...


@dataclass
class Lin:
    """The linearised problem at the plain estimate: residuals and Jacobian, distances apart."""

    r: np.ndarray  # (K, 3) mm
    j: np.ndarray  # (K, 3, P)
    dist_r: np.ndarray  # (D,) weighted distance residuals
    dist_j: np.ndarray  # (D, P) weighted


def lin_at(machine: Machine, artefact: Artefact, centres: Centres, est: Estimate) -> Lin:
    """The chain at ``est``: centre residuals, Jacobian and the weighted distance rows."""
    pred, jac = predict(machine, artefact, est.layout, est.p, centres, jacobian=True)
    dr, dj = np.zeros(0), np.zeros((0, est.layout.size))
    if est.layout.scale:
        d, jd, std = distance_rows(artefact, est.layout, est.p)
        cal = np.array([cd.distance_mm for cd in artefact.distances])
        dr, dj = (cal - d) / std, jd / std[:, None]
    return Lin(centres.xyz_mm - pred, jac, dr, dj)


def solve(lin: Lin, cols: np.ndarray, sigma_mm: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Weighted LS of r ≈ J δp + D θ: (step, residual (K,3), weighted residual, normalised
    Jacobian, column norms, smallest/largest singular value)."""
    a = np.concatenate([lin.j, cols], axis=2)
    n_par = a.shape[2]
    jw = (a / sigma_mm[None, :, None]).reshape(-1, n_par)
    rw = (lin.r / sigma_mm).ravel()
    if lin.dist_r.size:
        jw = np.vstack([jw, np.hstack([lin.dist_j, np.zeros((lin.dist_j.shape[0],
                                                               cols.shape[2]))])])
        rw = np.concatenate([rw, lin.dist_r])
    norms = np.linalg.norm(jw, axis=0)
    norms[norms == 0] = 1.0
    jn = jw / norms
    u, s, vt = np.linalg.svd(jn, full_matrices=False)
    step = (vt.T @ ((u.T @ rw) / s)) / norms
    res = lin.r - np.einsum("kip,p->ki", a, step)
    rw_res = rw - jw @ step
    return step, res, rw_res, jn, norms, float(s[-1] / s[0])


def fwls(lin: Lin, cols: np.ndarray, sigma_mm: np.ndarray, given: bool = False
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                    float]:
    """Two passes as ``estimate``: σ per axis from the first fit's residuals, then refit
    (one pass with a given σ)."""
    out = solve(lin, cols, sigma_mm)
    k = lin.r.shape[0]
    dof = k - (lin.j.shape[2] + cols.shape[2]) / 3.0
    if dof > 3 and not given:
        sig = np.sqrt(np.sum(out[1] ** 2, axis=0) / dof)
        if np.all(sig > 0):
            sigma_mm = sig
            out = solve(lin, cols, sigma_mm)
    return (*out[:5], sigma_mm, out[5])


def selection_share(lin: Lin, sigma_mm: np.ndarray, t: np.ndarray,
                    scored: list[tuple[float, Columns | None]], chosen: Columns,
                    touch: Any = None) -> np.ndarray:
    """Σ_m w_m Δ_m Δ_mᵀ over the link and setup parameters, then the drift over the run of X,
    Y and Z (model units; 0 for an axis a model leaves out): the spread of their estimates over
    the models BIC chose among (none included), w_m ∝ e^(−BIC_m/2), Δ_m model m's estimate −
    the chosen one's, in the linearisation at the plain estimate (the unconditional variance of
    Burnham & Anderson, *Model Selection and Multimodel Inference*, 2002, §4.3.2, about the
    estimate reported). A choice among close models is an uncertainty of the links: on the
    optimised plan under a 10 µm warm-up, the 15 % of runs where BIC added a spurious axis
    covered their links at 83-93 % within 2u without it. It is one of the drift too: an axis
    kept on a gain BIC barely grants is the one whose drift the other models put elsewhere.
    ``touch``: the centres' ``identification.drift.Touches`` (or None), as the columns take
    it."""
    bic = np.array([b for b, _ in scored])
    w = np.exp(-(bic - bic.min()) / 2.0)
    w /= w.sum()
    n = lin.j.shape[2]

    def params(model: Columns | None) -> np.ndarray:
        cols = np.zeros((len(t), 3, 0)) if model is None else model.columns(t, touch)
        step = solve(lin, cols, sigma_mm)[0]
        over = np.zeros(3)  # the drift over the run is the columns' parameter, per axis
        for j, a in enumerate(() if model is None else model.axes):
            over["XYZ".index(a)] = step[n + j]
        return np.concatenate([step[:n], over])

    p0 = params(chosen)
    out = np.zeros((n + 3, n + 3))
    for wi, (_, model) in zip(w, scored, strict=True):
        if wi > 1e-6 and model != chosen:
            d = params(model) - p0
            out += wi * np.outer(d, d)
    return out
