"""Upper-tail probabilities of the F, Student t and χ² distributions, as scipy.stats gives them.

scipy.stats' ``f.sf``, ``t.sf`` and ``chi2.sf`` are the regularised incomplete beta and gamma
functions behind argument checks. Importing even scipy.special costs ~0.17 s CPU (its array-API
layer), a sixth of the diagnosis of a 14-pose log, which tests one statistic at a time. So the two
functions are evaluated here by their continued fractions with modified Lentz's method
(Press et al., Numerical Recipes 3rd ed. §6.2, §6.4; the same expansions Cephes uses): the smaller
tail is computed directly, never as 1 − (something close to 1), so a deep tail keeps its relative
accuracy. tests/test_tails.py holds them to scipy.stats within 1e-9 relative over a grid of
statistics and degrees of freedom, edges included. Should an expansion not converge (it does in
a few hundred terms for degrees of freedom up to 1e6), scipy.special answers instead: never a
silently unconverged number. Scalars only.
"""

from __future__ import annotations

import math

_EPS = 1e-16  # relative size of the last continued-fraction factor at convergence
_TINY = 1e-300  # Lentz's guard against a zero denominator
_MAX_TERMS = 20_000


def _sf(x: float, *dfs: float) -> float | None:
    """scipy.stats' frame around ``_sf``: NaN for a NaN or a degree of freedom ≤ 0 (or NaN),
    0 at +∞; None: compute it."""
    x = float(x)
    if math.isnan(x) or not all(float(d) > 0 for d in dfs):
        return math.nan
    if x == math.inf:
        return 0.0
    return None


def _guard(v: float) -> float:
    return _TINY if abs(v) < _TINY else v


def _beta_cf(a: float, b: float, x: float) -> float | None:
    """The continued fraction of I_x(a, b) (NR §6.4, eq. 6.4.5), for x < (a + 1)/(a + b + 2)."""
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 / _guard(1.0 - qab * x / qap)
    h = d
    for m in range(1, _MAX_TERMS):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 / _guard(1.0 + aa * d)
        c = _guard(1.0 + aa / c)
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 / _guard(1.0 + aa * d)
        c = _guard(1.0 + aa / c)
        step = d * c
        h *= step
        if abs(step - 1.0) <= _EPS:
            return h
    return None


def _ibeta(a: float, b: float, x: float, y: float) -> float | None:
    """Regularised incomplete beta I_x(a, b), with y = 1 − x given separately (exact where x
    is close to 1). None: not converged."""
    if x <= 0.0:
        return 0.0
    if y <= 0.0:
        return 1.0
    log_front = (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
                 + a * math.log(x) + b * math.log(y))
    if x < (a + 1.0) / (a + b + 2.0):
        cf = _beta_cf(a, b, x)
        return None if cf is None else math.exp(log_front) * cf / a
    cf = _beta_cf(b, a, y)  # symmetry I_x(a, b) = 1 − I_y(b, a): the small side directly
    return None if cf is None else 1.0 - math.exp(log_front) * cf / b


def _gamma_q(a: float, x: float) -> float | None:
    """Regularised upper incomplete gamma Q(a, x) (NR §6.2: series for P below a + 1, Lentz's
    continued fraction for Q above). None: not converged."""
    if x <= 0.0:
        return 1.0
    log_front = -x + a * math.log(x) - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        ap = a
        for _ in range(_MAX_TERMS):
            ap += 1.0
            term *= x / ap
            total += term
            if abs(term) <= abs(total) * _EPS:
                return 1.0 - total * math.exp(log_front)
        return None
    bb = x + 1.0 - a
    c, d = 1.0 / _TINY, 1.0 / _guard(bb)
    h = d
    for i in range(1, _MAX_TERMS):
        an = -i * (i - a)
        bb += 2.0
        d = 1.0 / _guard(an * d + bb)
        c = _guard(bb + an / c)
        step = d * c
        h *= step
        if abs(step - 1.0) <= _EPS:
            return math.exp(log_front) * h
    return None


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """P(F(dfn, dfd) > x), as ``scipy.stats.f.sf``."""
    if (edge := _sf(x, dfn, dfd)) is not None:
        return edge
    x, dfn, dfd = float(x), float(dfn), float(dfd)
    if x <= 0.0:
        return 1.0
    # P(F > x) = I_w(dfd/2, dfn/2), w = dfd / (dfd + dfn x) (Abramowitz & Stegun 26.6.2)
    s = dfd + dfn * x
    v = _ibeta(dfd / 2.0, dfn / 2.0, dfd / s, dfn * x / s)
    if v is None:
        from scipy import special

        return float(special.fdtrc(dfn, dfd, x))
    return min(max(v, 0.0), 1.0)


def chi2_sf(x: float, df: float) -> float:
    """P(χ²(df) > x), as ``scipy.stats.chi2.sf``."""
    if (edge := _sf(x, df)) is not None:
        return edge
    x, df = float(x), float(df)
    if x <= 0.0:
        return 1.0
    v = _gamma_q(df / 2.0, x / 2.0)
    if v is None:
        from scipy import special

        return float(special.chdtrc(df, x))
    return min(max(v, 0.0), 1.0)


def t_sf(x: float, df: float) -> float:
    """P(t(df) > x), as ``scipy.stats.t.sf`` (support the whole line)."""
    if (edge := _sf(x, df)) is not None:
        return edge
    x, df = float(x), float(df)
    if x == -math.inf:
        return 1.0
    if x == 0.0:
        return 0.5
    # P(|t| > |x|) = I_w(df/2, 1/2), w = df / (df + x²) (A&S 26.7.1); half of it on each side
    s = df + x * x
    two_sided = _ibeta(df / 2.0, 0.5, df / s, x * x / s) if math.isfinite(s) else 0.0
    if two_sided is None:
        from scipy import special

        return float(special.stdtr(df, -x))
    upper = 0.5 * two_sided
    return min(max(upper if x > 0 else 1.0 - upper, 0.0), 1.0)
