"""What a stated standard uncertainty means: Type A with ν degrees of freedom (GUM-S1, GUM G.3).

Without a given probing repeatability the estimator's σ is a posteriori: s from the residuals,
resting on ν degrees of freedom (``Estimate.sigma_dof``). A parameter's error over s·√c (c its
diagonal element of (JᵀWJ)⁻¹) then follows Student's t with ν dof, not a normal, and ±2·s·√c
covers only P(|t_ν| ≤ 2): 94.3 % at the ν ≈ 24 of the 14-pose shift plan (measured on 100
simulated drift-free runs: 93.1 %). The standard uncertainty stated everywhere (reports, JSON,
judge, compensation, HMI, fleet) is therefore the standard deviation of that t distribution,
u = s·√c·√(ν/(ν−2)) (JCGM 101:2008, GUM-S1 6.4.9.4), so that ±2u covers ≥ 95 % for any ν ≥ 3
(95.3 % at ν = 24, 95.45 % as ν → ∞); a given σ (ν = ∞) leaves u as it was. Where a coverage
probability is asked for (the judge's guard band, the compensation's expanded uncertainty),
k is the t quantile over that same factor (``coverage_factor``).
"""

from __future__ import annotations

import math

NORMAL_2SIGMA = 0.9544997361036416  # P(|z| ≤ 2), erf(√2): the coverage ±2u keeps for ν < 3


def t_variance_factor(dof: float) -> float:
    """u² / (s²c): ν/(ν−2), 1 for ν = ∞. Below ν = 3 (the t's variance is infinite or nearly)
    the factor that makes ±2u cover what ±2σ of a normal does (95.45 %)."""
    if not math.isfinite(dof):
        return 1.0
    if dof >= 3.0:
        return dof / (dof - 2.0)
    if dof <= 0.0:
        raise ValueError(f"degrees of freedom must be positive, got {dof}")
    from scipy.stats import t  # rare: a fit with almost no redundancy (kept out of the CLI)

    return (float(t.ppf(0.5 + NORMAL_2SIGMA / 2.0, dof)) / 2.0) ** 2


def coverage_factor(sigma_dof: float, coverage: float = 0.9973) -> float:
    """k such that ±k·u covers ``coverage`` of an estimate whose stated u (above) rests on a
    σ estimated with ``sigma_dof`` degrees of freedom: t_q(ν)/√(ν/(ν−2)); the normal quantile
    as ν → ∞ (3.0 for 99.73 %, 1.96 for 95 %). With the 4-pose LinuxCNC plan (ν ≈ 8.3) it is
    3.67 for 99.73 % (4.2 times s): the t's tails are heavy beyond its standard deviation."""
    from scipy.stats import norm, t

    q = 0.5 + coverage / 2.0
    if not math.isfinite(sigma_dof):
        return float(norm.ppf(q))
    return float(t.ppf(q, sigma_dof)) / math.sqrt(t_variance_factor(sigma_dof))


def expanded_k(sigma_dof: float, normal_k: float) -> float:
    """The k at the coverage ``normal_k`` has for a normal (2 → 95.45 %) for a u on
    ``sigma_dof`` dof: what the judge's guard band and the compensation's U multiply u by."""
    if normal_k <= 0 or not math.isfinite(sigma_dof):
        return max(normal_k, 0.0)  # a given σ: the normal's k (and no scipy.stats import)
    return coverage_factor(sigma_dof, math.erf(normal_k / math.sqrt(2.0)))
