"""Effects the user already models (``rumba gap --known``): in the twin, and in the report."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from identification.effects import Effect, EffectContext
from identification.gap.attribute import Candidate, effect_params, typical_size
from identification.gap.data import Groups
from identification.gap.linear import FullFit, Problem, projected
from identification.gap.twin import Twin, effect_columns


def add_known(problem: Problem, known: Sequence[tuple[Effect, np.ndarray | None]], twin: Twin,
               groups: Groups, ctx: EffectContext, ball_jac: np.ndarray, base_pred_mm: np.ndarray
               ) -> tuple[list[tuple[Effect, np.ndarray]], list[Candidate]]:
    """Effects the twin already models. Given parameters: their contribution leaves the
    observations. Parameters to fit: their visible directions (as for a candidate) join the
    twin's columns, so every fold refits them with the setup and links on its training data
    and the gap is what remains."""
    fixed, fitted = [], []
    for eff, theta in known:
        cols = effect_columns(eff, twin, groups, ctx, ball_jac, base_pred_mm)
        if theta is not None:
            theta = np.asarray(theta, float)
            problem.y_um = problem.y_um - cols @ theta
            fixed.append((eff, theta))
            continue
        _, r, basis = projected(problem, problem.base, cols, typical_size(eff))
        fitted.append(Candidate(eff, np.einsum("gom,mr->gor", cols, basis), r, basis))
    if fitted:
        problem.base = np.concatenate([problem.base, *[c.cols for c in fitted]], axis=2)
        problem._base_u = None
    return fixed, fitted


def known_report(fixed: list[tuple[Effect, np.ndarray]], fitted: list[Candidate],
                  full: FullFit, n_twin: int) -> list[dict]:
    out = [{"effect": e.family, "axis": e.axis, "fitted": False, "visible_dof": None,
            "n_params": e.n_params,
            "params": {n: {"value": float(v), "std": None, "unit": u} for n, v, u in
                       zip(e.param_names, theta, e.units, strict=True)}} for e, theta in fixed]
    at = n_twin
    for c in fitted:
        r = c.cols.shape[2]
        params = effect_params(c.effect, c.basis, full.beta[at:at + r],
                               full.cov[at:at + r, at:at + r]) if r else {}
        at += r
        out.append({"effect": c.effect.family, "axis": c.effect.axis, "fitted": True,
                    "visible_dof": c.visible_dof, "n_params": c.effect.n_params,
                    "params": params} | ({} if r else {"note": "not visible on this probing "
                                                       "pattern: nothing to fit"}))
    return out



