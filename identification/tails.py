"""Upper-tail probabilities of the F, Student t and χ² distributions, as scipy.stats gives them.

scipy.stats computes ``f.sf``, ``t.sf`` and ``chi2.sf`` with these same scipy.special functions
(``fdtrc``, ``stdtr``, ``chdtrc``) after its argument checks, which are repeated here: the same
numbers (tests/test_tails.py), without importing scipy.stats (~0.7 s CPU, more than the
diagnosis of a 14-pose log takes). Scalars only: the callers test one statistic at a time.
"""

from __future__ import annotations

import math


def _sf(x: float, *dfs: float) -> float | None:
    """scipy.stats' frame around ``_sf``: NaN for a NaN or a degree of freedom ≤ 0 (or NaN),
    1 at or below the support's lower end 0 (F, χ²), 0 at +∞; None: compute it."""
    x = float(x)
    if math.isnan(x) or not all(float(d) > 0 for d in dfs):
        return math.nan
    if x == math.inf:
        return 0.0
    return None


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """P(F(dfn, dfd) > x), as ``scipy.stats.f.sf``."""
    if (edge := _sf(x, dfn, dfd)) is not None:
        return edge
    if x <= 0.0:
        return 1.0
    from scipy import special

    return float(special.fdtrc(dfn, dfd, x))


def chi2_sf(x: float, df: float) -> float:
    """P(χ²(df) > x), as ``scipy.stats.chi2.sf``."""
    if (edge := _sf(x, df)) is not None:
        return edge
    if x <= 0.0:
        return 1.0
    from scipy import special

    return float(special.chdtrc(df, x))


def t_sf(x: float, df: float) -> float:
    """P(t(df) > x), as ``scipy.stats.t.sf`` (support the whole line)."""
    if (edge := _sf(x, df)) is not None:
        return edge
    if x == -math.inf:
        return 1.0
    from scipy import special

    return float(special.stdtr(df, -x))
