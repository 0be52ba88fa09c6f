"""The map estimator: links, map coefficients, probe and ball setups of every placement, by
Gauss-Newton on the exact chain (METHOD.md §3), with a weak Tikhonov prior on the map.

Steps: the covered range of each axis (the measured centres); the observable links and map terms
up to the degree cap (``observe``); a preliminary fit with all of them; the degree of each
axis chosen by cross-validation over visits (``order``); the final fit with σ per axis a
posteriori (feasible weighted least squares, as ``identification.estimate``); its covariance
the visit sandwich under the rotary index scatter (``scatter``) widened by the t of σ's
degrees of freedom (``identification.uncertainty``).

The prior: every map coefficient ~ N(0, τ²), τ = ``PRIOR_UM`` µm for a translation and
``PRIOR_URAD`` µrad for a rotation per Legendre coefficient — several times the errors of a
machine worth mapping, so a well-observed term does not feel it (its data σ is a fraction of a
µm), while a term the poses barely separate from the others (a high degree near the end of a
short range, an angular error on a short arm) is held near zero instead of swinging by
millimetres; its stated u then is about τ, and says so.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.estimate import a_posteriori, fit_status
from identification.kinematics import Machine
from identification.linmap.observe import Observability, observable_terms
from identification.linmap.order import OrderChoice, choose_degrees
from identification.linmap.problem import (
    JointLayout,
    MapError,
    Placement,
    covered_ranges,
    evaluate,
)
from identification.linmap.refit import refit_centres
from identification.linmap.scatter import joint_sandwich
from identification.linmap.terms import MapBasis, candidate_terms
from identification.uncertainty import t_variance_factor

MAX_DEGREE = 4  # cap of the Legendre degree per axis (the data choose up to it)
PRIOR_UM = 50.0
PRIOR_URAD = 100.0
DEFAULT_SIGMA_UM = 1.0
STEP_TOL_MM = 1e-9
ANGLE_LENGTH_MM = 1000.0
MAX_ITER = 20


@dataclass(frozen=True)
class MapOptions:
    max_degree: int = MAX_DEGREE
    degrees: Mapping[str, int] | None = None  # fixed degrees per axis (no cross-validation)
    prior_um: float = PRIOR_UM
    prior_urad: float = PRIOR_URAD
    sigma_um: Sequence[float] | None = None  # stated centre repeatability x, y, z
    visit_scatter: bool = True
    rotary_repeatability_urad: Mapping[str, float] | None = None


@dataclass
class MapEstimate:
    """The estimated map with links and setups (mm / rad inside) and their covariance."""

    layout: JointLayout
    placement_names: list[str]
    names: list[str]
    p: np.ndarray
    cov: np.ndarray
    observability: Observability
    order: OrderChoice | None
    residual_mm: list[np.ndarray]
    distance_residual_um: np.ndarray
    residual_rms_um: float
    sigma_um: np.ndarray
    sigma_given: bool
    sigma_dof: float
    iterations: int
    converged: bool
    condition_number: float
    prior_um: float
    prior_urad: float
    visit_scatter: dict[str, tuple[float, float, float]] | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    @property
    def basis(self) -> MapBasis:
        return self.layout.basis

    def links_si(self) -> dict[str, tuple[float, float, str]]:
        """{ISO name: (value, std, unit)}, µrad or µm."""
        out = {}
        for i, n in enumerate(self.layout.links):
            k = 1e6 if n[1] in "ABC" else 1e3
            out[n] = (float(self.p[i] * k), float(self.std[i] * k), "urad" if k > 1e3 else "um")
        return out

    def terms_si(self) -> list[tuple[str, float, float, str]]:
        """(term, value, std, unit) of every map coefficient, µm or µrad."""
        s = self.layout.map_slice
        return [(t.name, float(v * t.to_si), float(u * t.to_si), t.unit) for t, v, u
                in zip(self.basis.terms, self.p[s], self.std[s], strict=True)]


def _prior(layout: JointLayout, prior_um: float, prior_urad: float) -> np.ndarray:
    """(P,) the Tikhonov diagonal 1/τ² (internal units), 0 outside the map."""
    out = np.zeros(layout.size)
    tau = np.array([prior_urad * 1e-6 if t.rotation else prior_um * 1e-3
                    for t in layout.basis.terms])
    out[layout.map_slice] = 1.0 / tau**2
    return out


def _unit_len(layout: JointLayout) -> np.ndarray:
    u = np.ones(layout.size)
    for i, n in enumerate(layout.links):
        if n[1] in "ABC":
            u[i] = ANGLE_LENGTH_MM
    for i, t in enumerate(layout.basis.terms):
        if t.rotation:
            u[layout.map_slice.start + i] = ANGLE_LENGTH_MM
    return u


def _rows(machine: Machine, placements: Sequence[Placement], layout: JointLayout,
          p: np.ndarray, sigma_mm: np.ndarray, jacobian: bool
          ) -> tuple[np.ndarray, np.ndarray | None, list[np.ndarray], np.ndarray]:
    """Weighted data rows (centres, then distances): (rw, jw, residuals mm, distance res mm)."""
    ev = evaluate(machine, placements, layout, p, jacobian=jacobian)
    res = [pl.centres.xyz_mm - q for pl, q in zip(placements, ev.pred, strict=True)]
    dres = ev.dist_cal - ev.dist
    rw = np.concatenate([(r / sigma_mm).ravel() for r in res] + [dres / ev.dist_std])
    jw = None
    if jacobian:
        assert ev.jac is not None
        jw = np.vstack([(j / sigma_mm[None, :, None]).reshape(-1, layout.size) for j in ev.jac]
                       + [ev.dist_jac / ev.dist_std[:, None]])
    return rw, jw, res, dres


def _gauss_newton(machine: Machine, placements: Sequence[Placement], layout: JointLayout,
                  p: np.ndarray, sigma_mm: np.ndarray, prior: np.ndarray
                  ) -> tuple[np.ndarray, bool, int]:
    """Gauss-Newton with the prior's rows (√Λ p → 0), stopped on the step (thesis B.4)."""
    sq = np.sqrt(prior)
    unit = _unit_len(layout)
    for it in range(1, MAX_ITER + 1):
        rw, jw, _, _ = _rows(machine, placements, layout, p, sigma_mm, True)
        assert jw is not None
        a = np.vstack([jw, np.diag(sq)[sq > 0]])
        b = np.concatenate([rw, -(sq * p)[sq > 0]])
        norms = np.linalg.norm(a, axis=0)
        norms[norms == 0] = 1.0
        step = np.linalg.lstsq(a / norms, b, rcond=None)[0] / norms
        p = p + step
        if np.linalg.norm(step * unit) < STEP_TOL_MM:
            return p, True, it
    return p, False, MAX_ITER


def _sigma_axis(res: list[np.ndarray], n_par: int) -> tuple[np.ndarray, float] | None:
    r = np.concatenate(res)
    dof = len(r) - n_par / 3.0
    if dof <= 3:
        return None
    s = np.sqrt(np.sum(r**2, axis=0) / dof)
    return (s, dof) if np.all(s > 0) else None


def fit_map(machine: Machine, placements: Sequence[Placement],
            options: MapOptions = MapOptions()) -> MapEstimate:
    """Estimate the map, links and setups from ``placements`` (module docstring)."""
    if not placements:
        raise MapError("no placement to map from")
    names_seen = [pl.name for pl in placements]
    if len(set(names_seen)) != len(names_seen):
        raise MapError(f"placement names must be distinct, got {names_seen}")
    ranges = covered_ranges(machine, placements)
    fixed = dict(options.degrees) if options.degrees is not None else None
    cap = max(fixed.values(), default=0) if fixed is not None else options.max_degree
    cand = [t for t in candidate_terms("XYZ", cap)
            if fixed is None or t.degree <= fixed.get(t.axis, 0)]
    # an axis that never moved between centres has no function to map
    cand = [t for t in cand if ranges[t.axis][1] - ranges[t.axis][0] > 1e-6]
    obs = observable_terms(machine, placements, cand, ranges)
    n_balls = tuple(len(pl.artefact.balls) for pl in placements)
    layout = JointLayout(obs.links, MapBasis(ranges, obs.terms), n_balls)
    given = options.sigma_um is not None
    sig_um = np.broadcast_to(np.asarray(DEFAULT_SIGMA_UM if options.sigma_um is None
                                        else options.sigma_um, float), (3,)).copy()
    if np.any(sig_um <= 0):
        raise MapError(f"sigma_um must be positive, got {sig_um}")
    sigma_mm = sig_um * 1e-3
    prior = _prior(layout, options.prior_um, options.prior_urad)
    p, conv, it = _gauss_newton(machine, placements, layout, np.zeros(layout.size), sigma_mm,
                                prior)
    touched = placements  # with their touches: spheres again in the estimate's frame (refit)
    if any(pl.points_mm is not None for pl in placements):
        placements = refit_centres(machine, touched, layout, p)
        p, conv, it2 = _gauss_newton(machine, placements, layout, p, sigma_mm, prior)
        it += it2
    sigma_dof = math.inf
    if not given:
        _, _, res, _ = _rows(machine, placements, layout, p, sigma_mm, False)
        got = _sigma_axis(res, layout.size)
        if got is not None:
            sigma_mm, sigma_dof = got[0], got[1]
    order = None
    if fixed is None and layout.basis.size:
        order, layout, p = _choose(machine, placements, layout, p, sigma_mm, prior,
                                   options.max_degree)
        prior = _prior(layout, options.prior_um, options.prior_urad)
    p, conv2, it2 = _gauss_newton(machine, placements, layout, p, sigma_mm, prior)
    conv, it = conv and conv2, it + it2
    if any(pl.points_mm is not None for pl in placements):
        placements = refit_centres(machine, touched, layout, p)
        p, conv2, it2 = _gauss_newton(machine, placements, layout, p, sigma_mm, prior)
        conv, it = conv and conv2, it + it2
    if not given:  # σ per axis from the final model's residuals, then once more
        _, _, res, _ = _rows(machine, placements, layout, p, sigma_mm, False)
        got = _sigma_axis(res, layout.size)
        if got is not None:
            sigma_mm, sigma_dof = got[0], got[1]
            p, conv3, it3 = _gauss_newton(machine, placements, layout, p, sigma_mm, prior)
            conv, it = conv and conv3, it + it3
    return _finish(machine, placements, layout, p, sigma_mm, sigma_dof, given, prior, obs,
                   order, conv, it, options)


def _choose(machine: Machine, placements: Sequence[Placement], layout: JointLayout,
            p: np.ndarray, sigma_mm: np.ndarray, prior: np.ndarray, max_degree: int
            ) -> tuple[OrderChoice, JointLayout, np.ndarray]:
    """Cross-validated degrees (``order``) on the problem linearised at ``p``; the layout with
    those terms and ``p`` restricted to it."""
    rw, jw, _, dres = _rows(machine, placements, layout, p, sigma_mm, True)
    assert jw is not None
    y = rw + jw @ p  # the linear model in absolute parameters: y ≈ J p
    groups = np.concatenate(
        [np.repeat(pl.centres.pose.astype(np.int64) + i * 10**9, 3)
         for i, pl in enumerate(placements)] + [np.full(len(dres), -1, np.int64)])
    axis: list[str | None] = [None] * layout.size
    degree = [0] * layout.size
    for i, t in enumerate(layout.basis.terms):
        axis[layout.map_slice.start + i] = t.axis
        degree[layout.map_slice.start + i] = t.degree
    choice = choose_degrees(jw, y, groups, prior, axis, degree, max_degree)
    keep = [i for i, t in enumerate(layout.basis.terms) if t.degree <= choice.degrees[t.axis]]
    new = JointLayout(layout.links, layout.basis.subset(keep), layout.n_balls)
    q = np.concatenate([p[: layout.map_slice.start], p[layout.map_slice][keep],
                        p[layout.tip_slice.start:]])
    return choice, new, q


DISTANCE_Z = 10.0  # a calibrated distance this many of its σ off what the centres say: named


def _distance_warnings(placements: Sequence[Placement], dres_mm: np.ndarray) -> list[str]:
    """A calibrated distance the fit could not meet: a wrong artefact file (another artefact,
    a ball moved since calibration) distorts the whole map's scale, so it is said."""
    out, k = [], 0
    for pl in placements:
        for cd in pl.artefact.distances:
            r = float(dres_mm[k]) * 1e3
            if abs(r) > DISTANCE_Z * cd.std_um:
                out.append(f"{pl.name}: the calibrated distance {cd.ball_a}-{cd.ball_b} "
                           f"({cd.distance_mm:g} mm ± {cd.std_um:g} µm) is {r:+.1f} µm off what "
                           "the centres say: is it this artefact's certificate? The map's scale "
                           "rests on it")
            k += 1
    return out


def _finish(machine: Machine, placements: Sequence[Placement], layout: JointLayout,
            p: np.ndarray, sigma_mm: np.ndarray, sigma_dof: float, given: bool,
            prior: np.ndarray, obs: Observability, order: OrderChoice | None, conv: bool,
            it: int, options: MapOptions) -> MapEstimate:
    rw, jw, res, dres = _rows(machine, placements, layout, p, sigma_mm, True)
    assert jw is not None
    a = jw.T @ jw + np.diag(prior)
    full = np.vstack([jw, np.diag(np.sqrt(prior))[prior > 0]])
    norms = np.linalg.norm(full, axis=0)
    norms[norms == 0] = 1.0
    s = np.linalg.svd(full / norms, compute_uv=False)
    cond = float(s[0] / s[-1])
    cov = np.linalg.inv(a)
    sig_um = sigma_mm * 1e3
    cov, sig_um, sigma_dof, warns = a_posteriori(rw, layout.size, cov, sig_um, sigma_dof, given)
    scatter = None
    if options.visit_scatter:
        scatter = joint_sandwich(machine, placements, layout, p, sig_um * 1e-3, prior, given,
                                 options.rotary_repeatability_urad)
        if scatter is not None:
            cov = scatter.cov * t_variance_factor(sigma_dof)
            warns += list(scatter.warnings)
    _, more = fit_status(cond, conv, MAX_ITER)
    more += _distance_warnings(placements, dres)
    r = np.concatenate(res)
    return MapEstimate(
        layout=layout, placement_names=[pl.name for pl in placements],
        names=layout.names(placements), p=p, cov=cov, observability=obs, order=order,
        residual_mm=res, distance_residual_um=dres * 1e3,
        residual_rms_um=float(np.sqrt(np.mean(r**2)) * 1e3), sigma_um=sig_um,
        sigma_given=given, sigma_dof=sigma_dof, iterations=it, converged=conv,
        condition_number=cond, prior_um=options.prior_um, prior_urad=options.prior_urad,
        visit_scatter=None if scatter is None else scatter.components,
        warnings=warns + [w for w in more if not w.startswith("condition number")])
