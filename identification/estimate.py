"""The RUMBA estimator: setup errors alone (thesis ch. 3) or with link errors (ch. 4, annex B).

Residual = measured − predicted centre on the exact chain (``identification.model.predict``),
Gauss-Newton from zero, stopped on the parameter-step norm (thesis §B.4). Calibrated
ball-to-ball distances are extra observations that make the isotropic scale of the linear axes
a parameter (METHOD.md §3); without one that direction is unobservable and named as such.
Internal units mm / rad; the result offers µm / µrad accessors for reports.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.estimate_scatter import visit_sandwich
from identification.identifiability import RANK_TOL, identifiable_links
from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict
from identification.uncertainty import coverage_factor, t_variance_factor  # noqa: F401 (re-export)

DEFAULT_SIGMA_UM = 1.0  # prior centre std when no probing repeatability is given
ANGLE_LENGTH_MM = 1000.0  # an angle step counts as its effect at 1 m in the stop criterion
STEP_TOL_MM = 1e-9  # stop when the step moves nothing by more than 1 pm (thesis B.4)
MAX_ITER = 20
COND_WARN = 1e4  # column-normalised condition number above which the result carries a warning


class RankDeficientError(ValueError):
    """The pose set cannot separate the requested parameters; the message names them."""


@dataclass
class Estimate:
    """Estimated parameters (mm / rad / dimensionless scale) with standard uncertainties."""

    layout: Layout
    ball_ids: list[str]
    p: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    residual_mm: np.ndarray  # (K, 3) measured − predicted with every estimated parameter
    distance_residual_um: np.ndarray  # (D,) calibrated − estimated distances
    residual_rms_um: float
    condition_number: float
    sigma_um: np.ndarray  # (3,) centre std used for the covariance (given or a posteriori)
    sigma_given: bool
    iterations: int
    converged: bool
    status: str
    unobservable: list[str]  # named directions the data cannot see
    absorbed_by: dict[str, str]  # for each unobservable direction: what absorbs it
    warnings: list[str] = field(default_factory=list)
    # degrees of freedom behind sigma_um (inf when given): the per-axis σ of the weighted fit
    # rests on (centres − parameters / 3) residuals each (GUM G.3: widen k with few dof)
    sigma_dof: float = math.inf
    # per-visit scatter behind a sandwich covariance (estimate_scatter.py): component
    # → (σ, u(σ), p-value) in µrad / µm; None without it (visit_scatter=False, < 4 visits)
    visit_scatter: dict[str, tuple[float, float, float]] | None = None
    # the components ("index B") held at the machine file's stated repeatability, as the
    # sandwich decided (``estimate_scatter.with_stated``): reports read it, never re-derive it
    stated_used: tuple[str, ...] = ()
    # the sandwich's own warnings (a stated repeatability overridden), also in ``warnings``:
    # a refit that redoes the sandwich (the drift model's) replaces exactly these
    scatter_warnings: tuple[str, ...] = ()

    @property
    def names(self) -> list[str]:
        return self.layout.names(self.ball_ids)

    def links_si(self) -> dict[str, tuple[float, float, str]]:
        """{ISO name: (value, std, unit)} in µrad for rotations, µm for translations."""
        out = {}
        for i, name in enumerate(self.layout.links):
            rot = name[1] in "ABC"
            k = 1e6 if rot else 1e3
            out[name] = (float(self.p[i] * k), float(self.std[i] * k), "urad" if rot else "um")
        return out

    @property
    def balls_um(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.layout.ball_slice
        n = self.layout.n_balls
        return self.p[s].reshape(n, 3) * 1e3, self.std[s].reshape(n, 3) * 1e3

    @property
    def probe_um(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.layout.tip_slice
        return self.p[s] * 1e3, self.std[s] * 1e3

    @property
    def scale_um_per_m(self) -> tuple[float, float] | None:
        if not self.layout.scale:
            return None
        return float(self.p[-1] * 1e6), float(self.std[-1] * 1e6)

    def setup_only(self) -> np.ndarray:
        """The parameter vector with every link error (and scale) set to zero."""
        q = self.p.copy()
        q[: len(self.layout.links)] = 0.0
        if self.layout.scale:
            q[-1] = 0.0
        return q


def distance_rows(artefact: Artefact, layout: Layout, p: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted calibrated distances (mm), their Jacobian (D, P) and stds (mm)."""
    ids = artefact.ids
    _, dballs, _, _ = layout.unpack(p)
    w = artefact.nominal_mm + dballs
    d = np.empty(len(artefact.distances))
    jac = np.zeros((len(artefact.distances), layout.size))
    std = np.empty(len(artefact.distances))
    for k, cd in enumerate(artefact.distances):
        a, b = ids.index(cd.ball_a), ids.index(cd.ball_b)
        v = w[a] - w[b]
        d[k] = np.linalg.norm(v)
        u = v / d[k]
        s = layout.ball_slice.start
        jac[k, s + 3 * a : s + 3 * a + 3] = u
        jac[k, s + 3 * b : s + 3 * b + 3] = -u
        std[k] = cd.std_um * 1e-3
    return d, jac, std


def _null_direction(jn: np.ndarray, names: list[str]) -> str:
    vt = np.linalg.svd(jn, full_matrices=False)[2]
    v = vt[-1]
    idx = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) > 0.1 * np.abs(v).max()][:5]
    return " ".join(f"{'+' if v[i] * v[idx[0]] > 0 else '-'} {names[i]}" for i in idx)[2:]


def _weighted(machine: Machine, artefact: Artefact, layout: Layout, p: np.ndarray,
              centres: Centres, sigma_mm: np.ndarray, use_dist: bool
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    pred, jac = predict(machine, artefact, layout, p, centres, jacobian=True)
    res = centres.xyz_mm - pred
    rw = (res / sigma_mm).ravel()
    jw = (jac / sigma_mm[None, :, None]).reshape(-1, layout.size)
    dres = np.zeros(0)
    if use_dist:
        d, dj, dstd = distance_rows(artefact, layout, p)
        cal = np.array([cd.distance_mm for cd in artefact.distances])
        dres = cal - d
        rw = np.concatenate([rw, dres / dstd])
        jw = np.vstack([jw, dj / dstd[:, None]])
    return rw, jw, res, dres


def _residuals(machine: Machine, artefact: Artefact, layout: Layout, p: np.ndarray,
               centres: Centres, sigma_mm: np.ndarray, use_dist: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pred, _ = predict(machine, artefact, layout, p, centres)
    res = centres.xyz_mm - pred
    rw = (res / sigma_mm).ravel()
    dres = np.zeros(0)
    if use_dist:
        d, _, dstd = distance_rows(artefact, layout, p)
        dres = np.array([cd.distance_mm for cd in artefact.distances]) - d
        rw = np.concatenate([rw, dres / dstd])
    return rw, res, dres


def estimate(
    machine: Machine,
    artefact: Artefact,
    centres: Centres,
    links: Sequence[str] | None = None,
    *,
    use_distances: bool = True,
    sigma_um: float | Sequence[float] | None = None,
    max_iter: int = MAX_ITER,
    visit_scatter: bool = True,
    rotary_repeatability_urad: Mapping[str, float] | None = None,
) -> Estimate:
    """Estimate setup errors and ``links`` (None: the identifiable set; () : setup only).

    ``sigma_um`` is the probing repeatability of a centre (scalar or x, y, z); given, it fixes
    the weights and the covariance; omitted, σ is estimated per axis from the residuals of a
    first fit, the fit is repeated with those weights and the covariance is a posteriori.
    Raises ``RankDeficientError`` naming the inseparable combination for a poor pose set.
    ``visit_scatter``: the covariance is the sandwich under the rotary index scatter (every
    ball of a visit moving together) estimated by REML, ~0 where the run shows none
    (``estimate_scatter``); False: independent centres. ``rotary_repeatability_urad``: the
    machine file's stated repeatability (µrad 1σ by rotary axis letter), the sandwich's index
    component for that axis unless the run shows it significantly worse (then a warning).
    """
    if len(centres) == 0:
        raise RankDeficientError("no ball centre to estimate from")
    finite = (np.isfinite(centres.xyz_mm).all(axis=1) & np.isfinite(centres.b_deg)
              & np.isfinite(centres.c_deg))
    if not finite.all():  # the SVD below would fail with a bare LinAlgError
        bad = sorted({int(p) for p in centres.pose[~finite]})
        raise ValueError(f"centres of poses {bad[:10]} are not finite numbers")
    try:
        ident = identifiable_links(machine, artefact, centres)
    except ValueError:
        ident = None  # the setup alone is not separable: the SVD check below names why
    chosen = tuple(() if ident is None else ident.links) if links is None else tuple(links)
    check_links(machine, chosen)
    use_dist = bool(use_distances and artefact.distances)
    layout = Layout(chosen, len(artefact.balls), scale=use_dist)
    names = layout.names(artefact.ids)
    given = sigma_um is not None
    sig_um = np.broadcast_to(np.asarray(DEFAULT_SIGMA_UM if sigma_um is None else sigma_um,
                                        float), (3,)).copy()
    if np.any(sig_um <= 0):
        raise ValueError(f"sigma_um must be positive, got {sig_um}")
    sigma_mm = sig_um * 1e-3
    unit_len = np.ones(layout.size)
    unit_len[[i for i, n in enumerate(layout.links) if n[1] in "ABC"]] = ANGLE_LENGTH_MM
    if layout.scale:
        unit_len[-1] = ANGLE_LENGTH_MM

    def solve(p: np.ndarray, sigma_mm: np.ndarray) -> tuple:
        """Gauss-Newton from ``p`` with centre weights 1/σ per axis (thesis B.4 stop rule)."""
        converged, it = False, 0
        rw, jw, res, dres = _weighted(machine, artefact, layout, p, centres, sigma_mm, use_dist)
        norms = np.linalg.norm(jw, axis=0)
        if np.any(norms == 0):
            zero = [names[i] for i in np.flatnonzero(norms == 0)]
            raise RankDeficientError(f"parameters {zero} have no effect on these centres "
                                     "(a ball never measured?)")
        jn = jw / norms
        s = np.linalg.svd(jn, compute_uv=False)
        if jn.shape[0] < jn.shape[1] or s[-1] < RANK_TOL * s[0]:
            raise RankDeficientError(
                f"rank-deficient pose set: {len(centres)} centres cannot separate "
                f"{_null_direction(jn, names)} (condition number "
                f"{s[0] / max(s[-1], 1e-300):.3g}); add indexations with other B/C values or "
                "estimate fewer link errors (--links)")
        for _ in range(max_iter):
            it += 1
            step = np.linalg.lstsq(jn, rw, rcond=None)[0] / norms
            p = p + step
            if np.linalg.norm(step * unit_len) < STEP_TOL_MM:
                # A step this small changes the Jacobian by nothing measurable: only the
                # residuals are refreshed (one prediction without derivatives).
                converged = True
                rw, res, dres = _residuals(machine, artefact, layout, p, centres, sigma_mm,
                                           use_dist)
                break
            rw, jw, res, dres = _weighted(machine, artefact, layout, p, centres, sigma_mm,
                                          use_dist)
            norms = np.linalg.norm(jw, axis=0)
            jn = jw / norms
        return p, converged, it, rw, jn, norms, res, dres

    p, converged, it, rw, jn, norms, res, dres = solve(np.zeros(layout.size), sigma_mm)
    dof_axis = len(centres) - layout.size / 3.0
    sigma_dof = math.inf
    if not given and dof_axis > 3:
        # The probing repeatability differs by axis (thesis §3.4: 0.66 / 0.98 / 0.44 µm), and a
        # single pooled σ mis-states the uncertainty of parameters that lean on one axis (seen
        # ×0.6 … ×1.3 on simulated runs). Feasible weighted least squares: σ per axis from the
        # residuals of the first fit, then one more solve with those weights.
        sig_axis = np.sqrt(np.sum(res**2, axis=0) / dof_axis)
        if np.all(sig_axis > 0):
            sigma_dof = dof_axis
            sigma_mm = sig_axis
            sig_um = sig_axis * 1e3
            p, converged2, it2, rw, jn, norms, res, dres = solve(p, sigma_mm)
            converged, it = converged and converged2, it + it2

    _, s, vt = np.linalg.svd(jn, full_matrices=False)
    cond = float(s[0] / s[-1])
    cov_n = (vt.T / s**2) @ vt
    cov = cov_n / np.outer(norms, norms)
    cov, sig_um, sigma_dof, warns = a_posteriori(rw, layout.size, cov, sig_um, sigma_dof, given)
    scatter = None
    if visit_scatter:
        dj = distance_rows(artefact, layout, p) if use_dist else (None, None, None)
        scatter = visit_sandwich(machine, artefact, layout, p, centres, sigma_mm, dj[1], dj[2],
                                 given=given, stated_urad=rotary_repeatability_urad)
        # the sandwich's components are estimated from the same residuals: same t widening
        cov = cov if scatter is None else scatter.cov * t_variance_factor(sigma_dof)
    status, more = fit_status(cond, converged, max_iter)
    unobs, absorbed = unobservable(layout, ident.dropped if ident else {})
    return Estimate(
        layout=layout, ball_ids=list(artefact.ids), p=p, std=np.sqrt(np.diag(cov)), cov=cov,
        residual_mm=res, distance_residual_um=dres * 1e3,
        residual_rms_um=float(np.sqrt(np.mean(res**2)) * 1e3), condition_number=cond,
        sigma_um=sig_um, sigma_given=given, iterations=it, converged=converged, status=status,
        unobservable=unobs, absorbed_by=absorbed, sigma_dof=sigma_dof,
        warnings=warns + more + list(scatter.warnings if scatter is not None else ()),
        visit_scatter=None if scatter is None else scatter.components,
        stated_used=() if scatter is None else scatter.stated_used,
        scatter_warnings=() if scatter is None else scatter.warnings,
    )


def check_links(machine: Machine, links: Sequence[str]) -> None:
    """Raise ``ValueError`` naming the link errors ``machine`` does not have."""
    unknown = [n for n in links if n not in machine.location_error_names()]
    if unknown:
        raise ValueError(f"unknown link errors {unknown}; this machine has "
                         f"{machine.location_error_names()}")


def a_posteriori(rw: np.ndarray, n_par: int, cov: np.ndarray, sig_um: np.ndarray,
                 sigma_dof: float, given: bool
                 ) -> tuple[np.ndarray, np.ndarray, float, list[str]]:
    """(cov, σ, its dof, warnings): without a given σ the covariance and σ are scaled by the
    variance factor of the weighted residuals ``rw`` (warned about when nothing is redundant),
    and the covariance by ν/(ν−2), ν its dof: the stated u is the standard deviation of the
    t distribution of a Type A estimate (GUM-S1 6.4.9.4, ``identification.uncertainty``)."""
    dof = rw.size - n_par
    warns: list[str] = []
    if not given:
        if dof > 0:
            var = float(rw @ rw) / dof
            cov = cov * var
            sig_um = sig_um * np.sqrt(var)
            sigma_dof = min(sigma_dof, float(dof))
            cov = cov * t_variance_factor(sigma_dof)
        else:
            warns.append("no redundancy (as many unknowns as equations): uncertainties are "
                         "those of a 1 µm centre repeatability, not a posteriori")
    return cov, sig_um, sigma_dof, warns


def fit_status(cond: float, converged: bool, max_iter: int) -> tuple[str, list[str]]:
    """(status, warnings) of a Gauss-Newton fit: poor conditioning, no convergence."""
    warns: list[str] = []
    if cond > COND_WARN:
        warns.append(f"condition number {cond:.3g} (column-normalised): some parameters are "
                     "poorly separated by these poses; see their uncertainties")
    status = "converged" if converged else f"not converged after {max_iter} iterations"
    if not converged:
        warns.append(f"Gauss-Newton {status}: the parameters may be inaccurate")
    return status, warns


def unobservable(layout: Layout, dropped: dict[str, str]
                 ) -> tuple[list[str], dict[str, str]]:
    """(unobservable directions, what absorbs each): the scale without a calibrated distance,
    then the ``dropped`` link errors."""
    unobs: list[str] = []
    absorbed: dict[str, str] = {}
    if not layout.scale:
        unobs.append("isotropic_scale")
        absorbed["isotropic_scale"] = ("the artefact geometry (ball setup errors): no calibrated "
                                       "distance, results are a volumetric distortion (thesis 3.5)")
    for name, by in dropped.items():
        unobs.append(name)
        absorbed[name] = by
    return unobs, absorbed
