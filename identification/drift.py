"""Slow TCP drift during a run (a warming machine) fitted with the links, chosen by BIC.

Model (seed 002 §3.3.4, ISO 230-3): a measured centre is the chain's prediction plus a drift
δ(t) of the controller X Y Z common to every ball, per axis linear in time or a first-order
warm-up A·(1 − e^(−t/τ)), t from the first centre of the run. It is parametrised by the drift
over the run θ_a = δ_a(T) (µm, T the run's span), linear for a given τ; τ is profiled over
``TAU_BOUNDS_S`` (one τ for every drifting axis: one thermal state).

Separability. A drift common to every ball is, at one instant, a rigid translation of all the
centres of a pose — exactly what a pose-dependent relocalisation does, and link translations
(EX0C …) and the stylus setup produce such translations too, as functions of B and C. So geometry
alone cannot tell a drift from links: only *time* can. Two visits of the same B/C at different
times (the plan's revisit) see identical link effects and different drifts; balls probed one
after the other within a pose see a drift that does not rotate with B/C as a setup error would;
a time order not monotone in C keeps δ(t(C)) out of the span of the link responses. Whether a
plan's timing achieves it is a rank question, answered on the augmented Jacobian
[J_links,setup | D_drift] (``separation``): a drift column whose part orthogonal to the link and
setup columns is below ``SEPARABLE_MIN`` of its norm is not separable, and is never fitted.

Choice: every separable model (each non-empty set of axes × linear / exponential) is fitted by
feasible weighted least squares in the linearisation at the plain estimate (the chain is affine
in µm-size changes to < 1 nm) and ranked by BIC on the per-axis concentrated Gaussian
likelihood, its parameter count k = links + setup + drifting axes (+ 1 for a fitted τ); the
drift model is kept only when its BIC beats the plain estimate's by ``BIC_MARGIN``. Otherwise
the plain estimate is returned untouched (today's numbers on a machine that stood still).
Kept, its shape (and τ) is fitted on every separable axis (``_every_axis``): BIC decides
whether the machine drifts and how, not which axes — one thermal state moves the tool in 3D,
and an axis left out for being small biases the others and the links. The links' covariance
is that model's (τ's column in it when τ is free, and the t's ν/(ν−2) of
``identification.uncertainty``) plus the spread of the link and drift estimates over the
shapes BIC weighed on those axes, no drift included (``_selection_share``): the choice is
part of their uncertainty. The
covariance is the visit sandwich of ``identification.estimate_scatter`` under the rotary axes'
index scatter estimated on the residuals the drift leaves, the drift's columns fitted too (as
the plain estimate's; before, the refit dropped it: 90.6 % 2u coverage on 8 warming
runs at 15 µrad, tests/test_drift_scatter.py).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from identification.brent import minimize_bounded
from identification.drift_lin import Lin, fwls, lin_at, solve
from identification.drift_lin import selection_share as _selection_share
from identification.drift_shape import DriftModel, Touches, shape_values
from identification.estimate import Estimate, a_posteriori, estimate
from identification.estimate_scatter import visit_sandwich
from identification.identifiability import RANK_TOL
from identification.kinematics import Machine
from identification.model import Artefact, Centres
from identification.uncertainty import t_variance_factor

TAU_BOUNDS_S = (300.0, 3600.0)  # 5 to 60 min: the warm-up of a machining centre (ISO 230-3)
MIN_SPAN_S = 30.0  # below this the centres of a run hardly have distinct times (the 6-pose
# plan `rumba plan` writes for the shift targets lasts 101 s and separates a drift well)
SEPARABLE_MIN = 0.05  # orthogonal fraction of a drift column the links and setup leave
BIC_MARGIN = 6.0  # "strong evidence" (Kass & Raftery 1995): on 40 drift-free simulated shift
# runs the best of the 14 drift models gained > 2.9 in 10 %, > 3.8 in 5 % (its choice among
# many is a search the plain BIC penalty does not pay for)
_GRID = 9  # log-spaced τ values of the profile before its bounded refinement


@dataclass
class DriftFit:
    """The fitted drift: per axis the drift over the run (µm) ± u; τ (s) ± u for a warm-up."""

    model: DriftModel
    span_s: float
    over_run_um: dict[str, tuple[float, float]]
    tau_s: tuple[float, float | None] | None  # (value, u); u None when τ sits on a bound
    tau_bounded: str | None  # "lower" / "upper" bound reached, else None
    bic_gain: float  # BIC(no drift) − BIC(this model)
    link_inflation: float  # largest u(link) with the drift / u(link) without
    start_t_s: float = 0.0

    def drift_mm(self, t_s: np.ndarray) -> np.ndarray:
        """(K, 3) the fitted drift at times ``t_s`` (absolute, same clock as the fit)."""
        t = np.asarray(t_s, float)
        # the fit's own origin and span: a held-out centre probed before the first estimate
        # centre (t < start) must not move the origin of every other
        f = shape_values(self.model.shape, t, self.model.tau_s, self.start_t_s, self.span_s)
        out = np.zeros((*t.shape, 3))
        for a, (v, _) in self.over_run_um.items():
            out[..., "XYZ".index(a)] = v * 1e-3 * f
        return out

    def centre_drift_mm(self, centres: Centres) -> np.ndarray:
        """(K, 3) the fitted drift as each centre carries it: through its touches where it
        has them (``DriftModel.columns``), else at its time."""
        touch = Touches.of(centres)
        if touch is None:
            return self.drift_mm(centres.t_s)
        return np.einsum("knab,knb->ka", touch.sens, self.drift_mm(touch.t_s))

    def as_dict(self) -> dict:
        return {"shape": self.model.shape, "axes": list(self.model.axes),
                "span_s": round(self.span_s, 3),
                "over_run_um": {a: {"value": round(v, 4), "std": round(u, 4)}
                                for a, (v, u) in self.over_run_um.items()},
                "tau_s": None if self.tau_s is None else {
                    "value": round(self.tau_s[0], 1),
                    "std": None if self.tau_s[1] is None else round(self.tau_s[1], 1)},
                "tau_bounded": self.tau_bounded, "bic_gain": round(self.bic_gain, 3),
                "link_inflation": round(self.link_inflation, 4)}


@dataclass
class DriftOutcome:
    """What the drift search concluded: the estimate to use and why."""

    estimate: Estimate
    fit: DriftFit | None
    status: str  # selected | not_selected | not_separable | no_times | too_short
    message: str
    inseparable: list[str] = field(default_factory=list)  # "exponential Z" … the plan cannot see


def _bic(res: np.ndarray, n_par: int) -> float:
    """BIC of the per-axis concentrated Gaussian likelihood (σ_x, σ_y, σ_z free)."""
    k = res.shape[0]
    rss = np.maximum(np.sum(res**2, axis=0), 1e-30)
    return float(np.sum(k * np.log(rss / k)) + (n_par + 3) * math.log(3 * k))


@dataclass
class _Projector:
    """The link and setup columns, weighted with the plain estimate's σ, as an orthonormal
    basis: every candidate drift is then fitted by projecting it out (a few µs each)."""

    u: np.ndarray  # (3K + D, r)
    rw: np.ndarray  # weighted residuals of the plain estimate
    sigma_mm: np.ndarray
    k: int

    @classmethod
    def of(cls, lin: Lin, sigma_mm: np.ndarray) -> _Projector:
        n_par = lin.j.shape[2]
        jw = (lin.j / sigma_mm[None, :, None]).reshape(-1, n_par)
        rw = (lin.r / sigma_mm).ravel()
        if lin.dist_r.size:
            jw, rw = np.vstack([jw, lin.dist_j]), np.concatenate([rw, lin.dist_r])
        norms = np.linalg.norm(jw, axis=0)
        norms[norms == 0] = 1.0
        u, s, _ = np.linalg.svd(jw / norms, full_matrices=False)
        u = u[:, s > RANK_TOL * s[0]]
        rw = rw - u @ (u.T @ rw)  # ≈ 0 at the plain estimate; exact in the linearisation
        return cls(u, rw, sigma_mm, lin.r.shape[0])

    def perp(self, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(drift columns with the link/setup part removed, their weighted norms)."""
        dw = (cols / self.sigma_mm[None, :, None]).reshape(-1, cols.shape[2])
        dw = np.vstack([dw, np.zeros((self.u.shape[0] - dw.shape[0], dw.shape[1]))])
        return dw - self.u @ (self.u.T @ dw), np.linalg.norm(dw, axis=0)

    def separation(self, cols: np.ndarray) -> np.ndarray:
        """Per drift column, the fraction of its weighted norm the link and setup columns
        cannot absorb: 0 = a combination of them (inseparable), 1 = orthogonal to them."""
        perp, dn = self.perp(cols)
        return np.linalg.norm(perp, axis=0) / np.where(dn > 0, dn, 1.0)

    def residual(self, cols: np.ndarray) -> np.ndarray:
        """(K, 3) centre residuals (mm) with the drift ``cols`` fitted alongside."""
        e = self.rw
        if cols.shape[2]:
            perp, _ = self.perp(cols)
            e = e - perp @ np.linalg.lstsq(perp, self.rw, rcond=None)[0]
        e = e[: 3 * self.k].reshape(self.k, 3)
        return e * self.sigma_mm


def separation(lin_j: np.ndarray, sigma_mm: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``_Projector.separation`` for a bare Jacobian (K, 3, P) (the plan's check)."""
    lin = Lin(np.zeros(lin_j.shape[:2]), lin_j, np.zeros(0), np.zeros((0, lin_j.shape[2])))
    return _Projector.of(lin, sigma_mm).separation(cols)


def _candidates() -> list[DriftModel]:
    """Every axis set × shape; exponential ones at the lower τ bound (profiled later)."""
    out = []
    for n in (1, 2, 3):
        for axes in itertools.combinations("XYZ", n):
            out.append(DriftModel("linear", axes))
            out.append(DriftModel("exponential", axes, TAU_BOUNDS_S[0]))
    return out


def fit_drift(machine: Machine, artefact: Artefact, centres: Centres, base: Estimate,
              axes: str = "XYZ", stated_urad: dict[str, float] | None = None) -> DriftOutcome:
    """Search the drift models for ``centres`` given their plain estimate ``base``
    (``stated_urad``: the stated rotary repeatability ``base`` was estimated with)."""
    if centres.t_s.size != len(centres) or not np.all(np.isfinite(centres.t_s)):
        return DriftOutcome(base, None, "no_times", "no probing times: drift not modelled")
    t = np.asarray(centres.t_s, float)
    tc = Touches.of(centres)
    span = float(t.max() - t.min())
    if span < MIN_SPAN_S:
        return DriftOutcome(base, None, "too_short",
                            f"the run lasts {span:.0f} s (< {MIN_SPAN_S:.0f} s): drift not "
                            "modelled")
    lin = lin_at(machine, artefact, centres, base)
    proj = _Projector.of(lin, np.asarray(base.sigma_um, float) * 1e-3)
    n_base = lin.j.shape[2]
    bic0 = _bic(proj.residual(np.zeros((len(t), 3, 0))), n_base)
    inseparable = []
    best: tuple[float, DriftModel] | None = None
    scored: list[tuple[float, DriftModel | None]] = [(bic0, None)]
    for model in _candidates():
        if not set(model.axes) <= set(axes):
            continue
        sep = proj.separation(model.columns(t, tc))
        if np.any(sep < SEPARABLE_MIN):
            inseparable += [f"{model.shape} {a}" for a, s in zip(model.axes, sep, strict=True)
                            if s < SEPARABLE_MIN and len(model.axes) == 1]
            continue
        model, bic = _profile(proj, t, model, n_base, tc)
        scored.append((bic, model))
        if best is None or bic < best[0]:
            best = (bic, model)
    if best is None:
        return DriftOutcome(base, None, "not_separable",
                            "the plan cannot separate drift from links (no revisit, or a time "
                            "order that follows the indexations): drift not modelled",
                            sorted(set(inseparable)))
    gain = bic0 - best[0]
    if gain < BIC_MARGIN:
        return DriftOutcome(base, None, "not_selected",
                            f"no drift: BIC of the best drift model ({best[1].shape} "
                            f"{''.join(best[1].axes)}) {gain:+.1f} against none",
                            sorted(set(inseparable)))
    # BIC found a drift and its shape; it is estimated on every separable axis. A warm-up
    # moves the tool centre point in 3D: an axis BIC leaves out still drifts, by less than
    # its noise, and that drift goes into the links and the other axes (shift plan, 5 µm: a
    # left-out −1.5 µm Y drift moved the fitted Z by −0.8 µm, 3 u); an axis it keeps is kept
    # because its estimate came out large (its drift biased away from 0). Per-axis choice:
    # 94.6 % of the fitted (run, axis) drifts within 2u (N = 100, 5 µm); every axis: 95.0 %.
    chosen = _every_axis(scored, best[1])
    rivals = [(b, m) for b, m in scored if m is None or m.axes == chosen.axes]
    share = _selection_share(lin, proj.sigma_mm, t, rivals, chosen, tc)
    est, fit = _final(machine, artefact, centres, base, chosen, span, gain, share,
                      stated_urad)
    return DriftOutcome(est, fit, "selected", _message(fit), sorted(set(inseparable)))


def _every_axis(scored: list[tuple[float, DriftModel | None]], best: DriftModel) -> DriftModel:
    """The best model's shape on every separable axis: the scored model of that shape with
    the most axes that holds the best one's (the lowest BIC among equals; τ profiled)."""
    sup = [(len(m.axes), -b, m) for b, m in scored
           if m is not None and m.shape == best.shape and set(best.axes) <= set(m.axes)]
    return max(sup, key=lambda x: (x[0], x[1]))[2]


def _profile(proj: _Projector, t: np.ndarray, model: DriftModel, n_base: int,
             tc: Touches | None = None
             ) -> tuple[DriftModel, float]:
    """(model with its best τ, BIC): the exponential's τ profiled on a log grid, refined."""
    m = len(model.axes)
    if model.shape == "linear":
        return model, _bic(proj.residual(model.columns(t, tc)), n_base + m)

    def bic_at(log_tau: float) -> float:
        mod = replace(model, tau_s=float(math.exp(log_tau)))
        return _bic(proj.residual(mod.columns(t, tc)), n_base + m + 1)

    lo, hi = math.log(TAU_BOUNDS_S[0]), math.log(TAU_BOUNDS_S[1])
    grid = np.linspace(lo, hi, _GRID)
    vals = [bic_at(g) for g in grid]
    i = int(np.argmin(vals))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, _GRID - 1)]
    rx, rf, _ = minimize_bounded(bic_at, float(a), float(b), xatol=1e-3)
    x, v = (rx, rf) if rf < vals[i] else (float(grid[i]), vals[i])
    return replace(model, tau_s=float(math.exp(x))), v


def _final(machine: Machine, artefact: Artefact, centres: Centres, base: Estimate,
           model: DriftModel, span: float, gain: float, share: np.ndarray,
           stated_urad: dict[str, float] | None = None) -> tuple[Estimate, DriftFit]:
    """The selected model refitted on the exact chain (two linearisations), with covariance;
    a free τ adds its column (the derivative of the drift by τ) so the drift's u carries it,
    and the links' and the drift's carry the model choice's ``share`` (``_selection_share``)."""
    t = np.asarray(centres.t_s, float)
    cols0 = model.columns(t, Touches.of(centres))  # the model's columns: one build, reused
    est = base
    theta = np.zeros(len(model.axes))
    sig0 = np.asarray(base.sigma_um, float) * 1e-3
    for _ in range(2):
        lin = lin_at(machine, artefact, centres, est)
        lin.r = lin.r - np.einsum("kim,m->ki", cols0, theta)
        step, res, rw, jn, norms, sigma_mm, _ = fwls(lin, cols0, sig0,
                                                      base.sigma_given)
        p = est.p + step[: lin.j.shape[2]]
        theta = theta + step[lin.j.shape[2]:]
        est = replace(est, p=p)
    n_par = lin.j.shape[2]
    bounded = None
    cols = cols0
    if model.shape == "exponential":
        tau = float(model.tau_s)
        lo, hi = TAU_BOUNDS_S
        if tau <= lo * 1.01:
            bounded = "lower"
        elif tau >= hi * 0.99:
            bounded = "upper"
        else:  # ∂δ/∂τ at θ: one more column, in mm per s of τ
            h = tau * 1e-4
            tc = Touches.of(centres)
            dcol = (replace(model, tau_s=tau + h).columns(t, tc)
                    - replace(model, tau_s=tau - h).columns(t, tc)) / (2 * h)
            cols = np.concatenate([cols, np.einsum("kim,m->ki", dcol, theta)[..., None]],
                                  axis=2)
    lin = lin_at(machine, artefact, centres, est)
    lin.r = lin.r - np.einsum("kim,m->ki", cols0, theta)
    _, res, rw, jn, norms, cond = solve(lin, cols, sigma_mm)
    _, s, vt = np.linalg.svd(jn, full_matrices=False)
    cov = ((vt.T / s**2) @ vt) / np.outer(norms, norms)
    n_all = cov.shape[0]
    # the per-axis σ now rests on K − (P + m) / 3 residuals per axis (as ``estimate``)
    dof_axis = len(t) - n_all / 3.0
    dof0 = dof_axis if math.isfinite(base.sigma_dof) else math.inf
    cov, sig_um, sig_dof, warns = a_posteriori(rw, n_all, cov, sigma_mm * 1e3, dof0,
                                               base.sigma_given)
    # rotary index scatter moves the balls of a visit together: the sandwich of ``estimate``
    # on the residuals the drift leaves, the drift's columns fitted with the links
    dist = lin.dist_j if lin.dist_j.size else None
    scatter = visit_sandwich(machine, artefact, est.layout, est.p, centres, sigma_mm, dist,
                             np.ones(lin.dist_j.shape[0]), cols,
                             np.einsum("kim,m->ki", cols0, theta),
                             given=base.sigma_given, stated_urad=stated_urad)
    if scatter is not None:
        cov = scatter.cov * t_variance_factor(sig_dof)
    sw = () if scatter is None else scatter.warnings
    m = len(model.axes)
    # the choice's share (``_selection_share``: links, setup, then drift X Y Z) on the links,
    # the setup and the chosen axes' drift; τ's own column carries none (τ is the chosen's)
    into = np.r_[np.arange(n_par), n_par + np.arange(m)]
    of = np.r_[np.arange(n_par), n_par + np.array(["XYZ".index(a) for a in model.axes], int)]
    cov[np.ix_(into, into)] += share[np.ix_(of, of)]
    std = np.sqrt(np.diag(cov))
    over = {a: (float(theta[j]), float(std[n_par + j])) for j, a in enumerate(model.axes)}
    tau_out = None
    if model.shape == "exponential":
        tau_out = (float(model.tau_s), None if bounded else float(std[n_par + m]))
    n_l = len(base.layout.links)
    infl = float(np.max(std[:n_l] / np.maximum(base.std[:n_l], 1e-300))) if n_l else 1.0
    fit = DriftFit(model, span, over, tau_out, bounded, gain, infl, float(t.min()))
    out = replace(est, std=std[:n_par], cov=cov[:n_par, :n_par], residual_mm=res,
                  residual_rms_um=float(np.sqrt(np.mean(res**2)) * 1e3),
                  condition_number=float(1.0 / cond), sigma_um=sig_um, sigma_dof=sig_dof,
                  # the plain fit's verdict on a stated repeatability is this fit's to give:
                  # its sandwich's warnings and decision replace exactly the plain one's
                  warnings=[*_without(base.warnings, base.scatter_warnings), *warns, *sw],
                  visit_scatter=None if scatter is None else scatter.components,
                  stated_used=() if scatter is None else scatter.stated_used,
                  scatter_warnings=sw)
    return out, fit


def _without(warnings: list[str], drop: tuple[str, ...]) -> list[str]:
    """``warnings`` less one occurrence of each of ``drop`` (the plain fit's scatter warnings:
    by identity of the message, never a substring another warning may share)."""
    out = list(warnings)
    for w in drop:
        if w in out:
            out.remove(w)
    return out


def _message(fit: DriftFit) -> str:
    parts = ", ".join(f"{a} {v:+.2f} ± {u:.2f} µm" for a, (v, u) in fit.over_run_um.items())
    tau = ""
    if fit.tau_s is not None:
        v, u = fit.tau_s
        tau = (f", τ {v / 60:.1f} min" + (f" ± {u / 60:.1f}" if u is not None else
                                           f" (at its {fit.tau_bounded} bound)"))
    return (f"{fit.model.shape} drift over the run ({fit.span_s / 60:.1f} min): {parts}{tau}; "
            "the links are estimated with it")


def estimate_drift_aware(machine: Machine, artefact: Artefact, centres: Centres,
                         links=None, *, sigma_um=None, use_distances: bool = True,
                         rotary_repeatability_urad: dict[str, float] | None = None
                         ) -> DriftOutcome:
    """``estimate`` and, where the plan's timing separates it and BIC wants it, a drift
    (``rotary_repeatability_urad``: the machine file's, as ``estimate`` takes it)."""
    base = estimate(machine, artefact, centres, links, sigma_um=sigma_um,
                    use_distances=use_distances,
                    rotary_repeatability_urad=rotary_repeatability_urad)
    return fit_drift(machine, artefact, centres, base, stated_urad=rotary_repeatability_urad)
