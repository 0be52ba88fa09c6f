"""The exponential warm-up as a gap candidate: ``thermal_drift`` A·(1 − e^(−t/τ)) per
linear axis with τ profiled within ``TAU_BOUNDS_H``.

The library's ``thermal_drift`` is linear in time; a machine warming up follows a first-order
curve (seed 002 §3.3.4, ISO 230-3) that flattens within the run when τ is shorter than it, and a
straight line then leaves a curved residual in time no other family explains. For a given τ
the warm-up is linear in its amplitude, so the diagnosis' linear machinery applies unchanged:
per axis, τ is chosen by the training fit of twin + warm-up (a log grid, then a bounded
refinement) and the candidate enters the ranking as ``thermal_drift:<axis>`` with that τ. τ is
fitted on every training group, so leave-pose-out folds do not refit it; the time-block check
(``split.py``) then judges its extrapolation in time. τ's uncertainty comes from the curvature
of the whitened residual sum of squares in log τ (profile likelihood, Δχ² = 1).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from identification.brent import minimize_bounded
from identification.effects import Effect, make_effect
from identification.gap.attribute import Candidate, effect_params
from identification.gap.linear import Problem, columns, fit, held_out, projected
from identification.kinematics import Machine

TAU_BOUNDS_H = (5.0 / 60.0, 1.0)  # 5 to 60 min, the warm-up of a machining centre
_GRID = 7
CHI2_1_95 = 3.84  # one parameter's worth of whitened squares (τ)
# profiled warm-up → (τ h, u τ h, amplitude entry with τ's share in its u, or None)
_REGISTRY: dict[Effect, tuple[float, float | None, dict | None]] = {}


def warmup_effect(machine: Machine, axis: str, tau_h: float) -> Effect:
    """The exponential ``thermal_drift`` of ``axis`` at a fixed τ (its amplitude µm free); the
    note names τ, so effects of different τ never compare equal."""
    eff = make_effect("thermal_drift", axis, machine, model="exponential", tau_h=tau_h)
    return replace(eff, note=f"{eff.note}; warm-up, τ {tau_h!r} h profiled")


def candidates(machine: Machine, problem: Problem, base: np.ndarray,
               cols_of: Callable[[Effect], np.ndarray], typical: Callable[[Effect], np.ndarray],
               families: Sequence[str], known: set[str]) -> list[Candidate]:
    """One profiled warm-up candidate per linear axis (visible ones only)."""
    if "thermal_drift" not in families:
        return []
    out = []
    for axis in sorted(machine.linear_axes):
        if f"thermal_drift:{axis}" in known:
            continue
        cand = _profiled(machine, axis, problem, base, cols_of, typical)
        if cand is not None and _beats_line(machine, axis, cand, problem, base, cols_of,
                                            typical):
            out.append(cand)
    return out


def _beats_line(machine: Machine, axis: str, cand: Candidate, problem: Problem,
                base: np.ndarray, cols_of: Callable[[Effect], np.ndarray],
                typical: Callable[[Effect], np.ndarray]) -> bool:
    """A warm-up is offered only where its curve predicts held-out data better than the
    straight line by more than τ's own worth (χ²₁ at 95 %, 3.84 in whitened squares): τ was
    profiled on every group, held-out ones included, and a flat-enough exponential is a line."""
    eff = make_effect("thermal_drift", axis, machine)
    cols = cols_of(eff)
    _, r, basis = projected(problem, base, cols, typical(eff))
    if r == 0:
        return True
    line = held_out(problem, columns(problem, [np.einsum("gom,mr->gor", cols, basis)]))
    curve = held_out(problem, columns(problem, [cand.cols]))
    return curve.ss_w < line.ss_w - CHI2_1_95


def _profiled(machine: Machine, axis: str, problem: Problem, base: np.ndarray,
              cols_of: Callable[[Effect], np.ndarray], typical: Callable[[Effect], np.ndarray]
              ) -> Candidate | None:
    cache: dict[float, tuple[float, Candidate | None]] = {}

    def at(log_tau: float) -> float:
        if log_tau not in cache:
            eff = warmup_effect(machine, axis, math.exp(log_tau))
            cols = cols_of(eff)
            _, r, basis = projected(problem, base, cols, typical(eff))
            if r == 0:
                cache[log_tau] = (math.inf, None)
            else:
                c = Candidate(eff, np.einsum("gom,mr->gor", cols, basis), r, basis)
                cache[log_tau] = (fit(problem, columns(problem, [c.cols])).rss_w, c)
        return cache[log_tau][0]

    lo, hi = math.log(TAU_BOUNDS_H[0]), math.log(TAU_BOUNDS_H[1])
    grid = np.linspace(lo, hi, _GRID)
    vals = [at(float(g)) for g in grid]
    i = int(np.argmin(vals))
    if not math.isfinite(vals[i]) or i == _GRID - 1:
        return None  # τ at its upper bound: the curve is straightening, the line says it
    best = float(grid[i])
    if 0 < i < _GRID - 1:
        x, fx, _ = minimize_bounded(at, grid[i - 1], grid[i + 1], xatol=1e-3)
        if fx < vals[i]:
            best = float(x)
    cand = cache[best][1]
    assert cand is not None
    tau = math.exp(best)
    u, amp = None, None
    if 0 < i < _GRID - 1:  # curvature of the whitened RSS in log τ: Δχ² = 1 ↔ 1 σ
        h = 0.05
        curv = (at(best + h) - 2 * cache[best][0] + at(best - h)) / h**2
        if curv > 0:
            u = tau * math.sqrt(2.0 / curv)
            # the amplitude moves with τ along the profile: its u at fixed τ widened by
            # dA/d(ln τ) · u(ln τ) (first-order propagation, GUM 5.1.2)
            a0, a_hi, a_lo = (_amplitude(problem, cache[x][1]) for x in (best, best + h,
                                                                         best - h))
            slope = (a_hi["value"] - a_lo["value"]) / (2 * h)
            amp = dict(a0, std=math.hypot(a0["std"], slope * u / tau))
    if len(_REGISTRY) > 4096:  # a long-lived process diagnosing many logs
        _REGISTRY.clear()
    _REGISTRY[cand.effect] = (tau, u, amp)
    return cand


def _amplitude(problem: Problem, cand: Candidate | None) -> dict:
    """{value, std, unit} of the warm-up's amplitude fitted with the twin at the candidate's τ."""
    assert cand is not None
    full = fit(problem, columns(problem, [cand.cols]))
    n = problem.base.shape[2]
    r = cand.cols.shape[2]
    params = effect_params(cand.effect, cand.basis, full.beta[n:n + r],
                           full.cov[n:n + r, n:n + r])
    return next(iter(params.values()))


def tau_param(effect: Effect) -> dict[str, dict]:
    """The profiled τ of a warm-up candidate as a report parameter (h) and its amplitude with
    τ's share in its u (it replaces the fit's own at fixed τ), else nothing."""
    if effect not in _REGISTRY:
        return {}
    tau, u, amp = _REGISTRY[effect]
    out = {f"drift_{effect.axis}_tau": {"value": round(tau, 5),
                                        "std": None if u is None else round(u, 5), "unit": "h"}}
    if amp is not None:  # the amplitude's u with τ's share (merged over the fit's own)
        out = {f"drift_{effect.axis}_amplitude": amp} | out
    return out


def model_of(effect: Effect) -> dict[str, str]:
    """``{"model": "exponential"}`` for a profiled warm-up, ``linear`` for the library's
    thermal drift, nothing for other families (the verdict's selected entries)."""
    if effect in _REGISTRY:
        return {"model": "exponential"}
    return {"model": "linear"} if effect.family == "thermal_drift" else {}
