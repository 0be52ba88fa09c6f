"""Link uncertainties that hold under rotary index scatter: a sandwich on the estimate.

The estimator weights each centre coordinate independently (σ per axis, a posteriori). With
non-repeatable indexing every ball of a visit moves together, so the residuals of one visit
are correlated and the independent covariance understates the link uncertainties (measured: 2u
covered the truth in 84 % of the links at 10 µrad 1σ on the annex-B plan). The components of
``identification.visit_scatter`` — index errors of the rotary axes and an independent centre
scatter per axis — are estimated by REML on the estimate's residuals, and the covariance is
the sandwich A⁻¹ (Σ_v X_vᵀ W V_v W X_v) A⁻¹ of the same weighted estimate (A = XᵀWX;
calibrated distances keep their own, independent rows) under those estimates, always: a mixed
model's covariance with its REML components, ~0 for an index scatter the run does not show.
Before it was used only where an index component passed its boundary test at
p < 0.01, a pre-test estimator: below detection the scatter was there and ignored. On the same
40 simulated shift runs with 4 µrad B/C index scatter that gate covered the links within 2u in
91.6 %, the sandwich always 92.5 % (the independent covariance never: 92.5 %, error/u spread
1.10 against 1.07); without index scatter it moves u by +0.8 % on average, +5 % on the
link that leans most on the index columns (the same 40 runs, index scatter 0). A machine file's
stated rotary repeatability is the Type B input of its axis' index component (``with_stated``):
a few visits cannot pin σ, the data sheet can; its coverage against the components from the
run alone (benchmarks/bench_warmup.py) is the warm-up table ("A machine warming up
during the check"), where the figures live, kept current with each re-run.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict
from identification.visit_scatter import (
    LR_ALPHA,
    ScatterFit,
    VisitBlocks,
    arrange,
    covariance,
    estimate_components,
)

H_DEG = 1e-3
R0_UM2 = 1e-6  # nothing known beforehand: every variance is a component
STATED_TAG = "machine file states"  # in the warning of a stated repeatability overridden


@dataclass(frozen=True)
class VisitScatterCov:
    cov: np.ndarray  # (P, P) model units
    # name: (σ, u(σ), p) µrad / µm, the free REML estimates; with a stated repeatability also
    # "<name> stated": (stated σ, 0, p of the test σ = stated against free)
    components: dict[str, tuple[float, float, float]]
    warnings: tuple[str, ...] = ()  # a stated repeatability the run contradicts
    # the index components ("index B") whose stated σ the covariance is under: the test's
    # decision, made here once (``with_stated``), read by every report
    stated_used: tuple[str, ...] = ()


def visits_of(centres: Centres) -> np.ndarray:
    """Visit id per centre: its pose and how many times that ball was measured there before
    (repeats and revisits are new indexations)."""
    seen: dict[tuple[int, int], int] = {}
    out = np.zeros(len(centres), np.int64)
    order = np.argsort(centres.t_s, kind="stable") if centres.t_s.size else np.arange(
        len(centres))
    for i in order:
        key = (int(centres.pose[i]), int(centres.ball[i]))
        out[i] = int(centres.pose[i]) * 1000 + seen.get(key, 0)
        seen[key] = seen.get(key, 0) + 1
    return out


def visit_sandwich(machine: Machine, artefact: Artefact, layout: Layout, p: np.ndarray,
                   centres: Centres, sigma_mm: np.ndarray, dist_jac: np.ndarray | None,
                   dist_std_mm: np.ndarray | None, extra_cols: np.ndarray | None = None,
                   offset_mm: np.ndarray | None = None, given: bool = False,
                   stated_urad: Mapping[str, float] | None = None
                   ) -> VisitScatterCov | None:
    """The sandwich covariance of the weighted estimate at ``p`` (weights 1/σ² per axis,
    ``sigma_mm``) under the REML components; None with fewer than 4 visits or 2 rotary axes.
    ``extra_cols`` (K, 3, m): more fitted columns (mm per unit; a TCP drift), whose
    parameters come last in the covariance; ``offset_mm`` (K, 3): their fitted effect, taken
    off the centres (a drift moves every ball of a visit together, as an index error does:
    left in the residuals it would read as index scatter). ``given``: ``sigma_mm`` is the
    stated centre repeatability, used as the centre components (only the index ones are
    estimated), as the independent covariance uses it. ``stated_urad``: a rotary axis'
    stated repeatability (µrad 1σ by axis letter), used for its index component unless the
    run contradicts it (``with_stated``)."""
    visit = visits_of(centres)
    if len(np.unique(visit)) < 4 or len(machine.rotary_axes) < 2:
        return None
    pred, jac = predict(machine, artefact, layout, p, centres, jacobian=True)
    n_base = jac.shape[2]
    scale = np.ones(n_base)
    if extra_cols is not None:
        # an extra column (a τ derivative, µm per s) can be 1e-9 of a link's: scaled to the
        # links' median norm, or the pseudo-inverse below would drop it as rank-deficient
        norm = np.linalg.norm(jac.reshape(-1, n_base), axis=0)
        en = np.linalg.norm(extra_cols.reshape(-1, extra_cols.shape[2]), axis=0)
        f = np.where(en > 0, en / np.median(norm[norm > 0]), 1.0)
        scale = np.concatenate([scale, f])
        jac = np.concatenate([jac, extra_cols / f], axis=2)
        if dist_jac is not None and dist_jac.size:
            dist_jac = np.hstack([dist_jac, np.zeros((dist_jac.shape[0], extra_cols.shape[2]))])
    off = 0.0 if offset_mm is None else offset_mm
    y = (centres.xyz_mm - pred - off) * 1e3
    x = jac * 1e3
    z = np.zeros((len(centres), 3, 2))
    for k in range(2):
        moved = Centres(centres.pose, centres.ball, centres.b_deg + (H_DEG if k == 0 else 0.0),
                        centres.c_deg + (H_DEG if k == 1 else 0.0), centres.xyz_mm,
                        centres.t_s)
        q1, _ = predict(machine, artefact, layout, p, moved)
        z[:, :, k] = (q1 - pred) * 1e3 / (np.deg2rad(H_DEG) * 1e6)
    r0 = np.broadcast_to(R0_UM2 * np.eye(3), (len(centres), 3, 3)).copy()
    b = arrange(y, x, r0, z, visit)
    names = tuple([f"index {a}" for a in machine.rotary_axes[:2]] + ["centre x", "centre y",
                                                                      "centre z"])
    sig_um = np.asarray(sigma_mm, float) * 1e3
    centre = {2 + a: float(sig_um[a]) for a in range(3)} if given else {}
    start = [5.0, 5.0, *sig_um]
    # the tests' p-values are reported (``Estimate.visit_scatter``), never a gate
    fit = estimate_components(b, names, start, test=(0, 1), fixed=centre or None,
                              intervals=False)  # σ, u(σ) and p are reported, not the interval
    comps = {n: (float(fit.sigma[i]), float(fit.std[i]), float(fit.p_value[i]))
             for i, n in enumerate(names)}
    stated = {i: float(stated_urad[a]) for i, a in enumerate(machine.rotary_axes[:2])
              if stated_urad and a in stated_urad}
    theta, more, warns, used = with_stated(b, names, start, fit, centre, stated)
    comps.update(more)
    w = np.einsum("vna,a->vn", b.centre, 1.0 / sig_um**2)  # (V, n) weights of the live slots
    xw = b.x * w[..., None]
    a_mat = np.einsum("vnp,vnq->pq", xw, b.x)
    v = covariance(b, theta)
    meat = np.einsum("vnp,vnm,vmq->pq", xw, v, xw)
    if dist_jac is not None and dist_jac.size:
        dj = dist_jac / np.asarray(dist_std_mm)[:, None]
        a_mat = a_mat + dj.T @ dj
        meat = meat + dj.T @ dj
    a_inv = np.linalg.pinv(a_mat, rcond=1e-12)
    cov = a_inv @ meat @ a_inv / np.outer(scale, scale)
    return VisitScatterCov(cov, comps, warns, used)


def with_stated(b: VisitBlocks, names: tuple[str, ...], start: list[float], free: ScatterFit,
                fixed: dict[int, float], stated: dict[int, float]
                ) -> tuple[np.ndarray, dict[str, tuple[float, float, float]], tuple[str, ...],
                           tuple[str, ...]]:
    """(components the covariance is under, the stated ones' entries, warnings, the names of
    the components held at their stated value). A stated
    rotary repeatability (machine file, µrad 1σ per indexation: the builder's ISO 230-2 test)
    is a Type B input (GUM 4.3.1) for its index component: 7-8 visits cannot pin σ (σ̂ is a
    scaled χ with few dof; in the shift plan's runs with σ̂_B < 2 µrad at a true 4 the links
    covered 83 % within 2u, with the true σ given 94.4 %). The data keep their say: the free
    REML estimate is reported next to it, and where it exceeds the stated value significantly
    — likelihood ratio of σ = stated against free, one-sided (a repeatability better than
    stated contradicts nothing a link u rests on), p < ``LR_ALPHA`` — the estimate is used and
    a warning names the axis and both values. Without a stated value: the free estimate."""
    if not stated:
        return free.sigma, {}, (), ()
    out: dict[str, tuple[float, float, float]] = {}
    warns: list[str] = []
    keep: dict[int, float] = {}
    for i, s in stated.items():
        nll = estimate_components(b, names, start, fixed={**fixed, i: s}, test=False).nll
        lr = max(nll - free.nll, 0.0)
        # the signed root of the LR is ~N(0, 1) under σ = stated (½χ²₁ at a stated 0)
        p = 0.5 * math.erfc(math.sqrt(lr / 2.0)) if free.sigma[i] > s else 1.0
        out[f"{names[i]} stated"] = (s, 0.0, p)
        if p < LR_ALPHA:
            warns.append(f"{names[i][6:]} indexing repeatability {free.sigma[i]:.1f} µrad "
                         f"estimated, {STATED_TAG} {s:g} (likelihood-ratio test of σ = {s:g} "
                         f"µrad: p = {p:.2g} < {LR_ALPHA:g}): the estimate is used for the "
                         "link uncertainties; check the axis' clamping and the data sheet")
        else:
            keep[i] = s
    if not keep:
        return free.sigma, out, tuple(warns), ()
    used = estimate_components(b, names, start, fixed={**fixed, **keep}, test=False)
    return used.sigma, out, tuple(warns), tuple(names[i] for i in sorted(keep))
