"""The map's covariance under rotary index scatter: the visit sandwich of
``identification.estimate_scatter`` over every placement at once.

Every ball of one visit shares its index error; the components (index scatter of each rotary
axis, an independent centre scatter per axis) are one machine's, estimated by REML on the
residuals of all placements together (``identification.visit_scatter``), a machine file's
stated repeatability a Type B input for its axis (``estimate_scatter.with_stated``). The
estimate is the Tikhonov-regularised weighted least squares, A = XᵀWX + Λ (+ calibrated
distances); its covariance is A⁻¹ (Σ_v X_vᵀ W V_v W X_v + Λ) A⁻¹: the Bayesian posterior
covariance (XᵀWX + Λ)⁻¹ when the visits are independent with the weights' variances, the
sandwich when they are not.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from identification.estimate_scatter import H_DEG, R0_UM2, visits_of, with_stated
from identification.kinematics import Machine
from identification.linmap.problem import Evaluation, JointLayout, Placement, evaluate
from identification.visit_scatter import arrange, covariance, estimate_components

VISIT_STRIDE = 10**9  # visit ids of placement i start at i · VISIT_STRIDE


@dataclass(frozen=True)
class JointScatter:
    cov: np.ndarray
    components: dict[str, tuple[float, float, float]]
    warnings: tuple[str, ...]
    stated_used: tuple[str, ...]


def _index_columns(machine: Machine, placements: Sequence[Placement], layout: JointLayout,
                   p: np.ndarray, base: Evaluation) -> list[np.ndarray]:
    """(K, 3, 2) per placement: d(centre)/d(rotary index error) in µm per µrad."""
    out = []
    for k in range(2):
        moved = [Placement(pl.name, pl.artefact,
                           replace(pl.centres, b_deg=pl.centres.b_deg + (H_DEG if k == 0 else 0),
                                   c_deg=pl.centres.c_deg + (H_DEG if k == 1 else 0)))
                 for pl in placements]
        ev = evaluate(machine, moved, layout, p)
        out.append([(q1 - q0) * 1e3 / (np.deg2rad(H_DEG) * 1e6)
                    for q1, q0 in zip(ev.pred, base.pred, strict=True)])
    return [np.stack([out[0][i], out[1][i]], axis=2) for i in range(len(placements))]


def joint_sandwich(machine: Machine, placements: Sequence[Placement], layout: JointLayout,
                   p: np.ndarray, sigma_mm: np.ndarray, prior: np.ndarray, given: bool,
                   stated_urad: Mapping[str, float] | None = None) -> JointScatter | None:
    """The sandwich covariance at ``p`` (``prior``: the Tikhonov diagonal, 1/unit²); None with
    fewer than 4 visits or without two rotary axes."""
    visit = np.concatenate([visits_of(pl.centres) + i * VISIT_STRIDE
                            for i, pl in enumerate(placements)])
    if len(np.unique(visit)) < 4 or len(machine.rotary_axes) < 2:
        return None
    ev = evaluate(machine, placements, layout, p, jacobian=True)
    assert ev.jac is not None
    y = np.concatenate([pl.centres.xyz_mm - q for pl, q in zip(placements, ev.pred,
                                                               strict=True)]) * 1e3
    x = np.concatenate(ev.jac) * 1e3
    z = np.concatenate(_index_columns(machine, placements, layout, p, ev))
    r0 = np.broadcast_to(R0_UM2 * np.eye(3), (len(y), 3, 3)).copy()
    b = arrange(y, x, r0, z, visit)
    names = tuple([f"index {a}" for a in machine.rotary_axes[:2]]
                  + ["centre x", "centre y", "centre z"])
    sig_um = np.asarray(sigma_mm, float) * 1e3
    centre = {2 + a: float(sig_um[a]) for a in range(3)} if given else {}
    start = [5.0, 5.0, *sig_um]
    # σ only: the p-values and likelihood intervals of the daily estimate are not needed for
    # a covariance and cost most of the time (a 2-placement map: 60 s of 85)
    fit = estimate_components(b, names, start, test=False, fixed=centre or None)
    comps = {n: (float(fit.sigma[i]), float(fit.std[i]), float(fit.p_value[i]))
             for i, n in enumerate(names)}
    stated = {i: float(stated_urad[a]) for i, a in enumerate(machine.rotary_axes[:2])
              if stated_urad and a in stated_urad}
    theta, more, warns, used = with_stated(b, names, start, fit, centre, stated)
    comps.update(more)
    w = np.einsum("vna,a->vn", b.centre, 1.0 / sig_um**2)
    xw = b.x * w[..., None]
    a_mat = np.einsum("vnp,vnq->pq", xw, b.x) + np.diag(prior)
    meat = np.einsum("vnp,vnm,vmq->pq", xw, covariance(b, theta), xw) + np.diag(prior)
    if len(ev.dist):
        dj = ev.dist_jac / ev.dist_std[:, None]
        a_mat = a_mat + dj.T @ dj
        meat = meat + dj.T @ dj
    a_inv = np.linalg.pinv(a_mat, rcond=1e-14)
    return JointScatter(a_inv @ meat @ a_inv, comps, warns, used)
