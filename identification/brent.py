"""Brent's minimiser of a function of one variable on an interval, without importing scipy.

Golden section and successive parabolic interpolation, Brent's ``localmin`` (Algorithms for
Minimization without Derivatives, 1973, ch. 5) as Forsythe, Malcolm & Moler give it (``fmin``,
Computer Methods for Mathematical Computations, 1977, §8.2), with the tolerances of
``scipy.optimize.minimize_scalar(method="bounded")``: the same steps, so the same minimum to the
last bit (tests/test_brent.py), at none of scipy.optimize's import cost (0.4 s CPU, more than
the rest of an analysis of a 14-pose log).
"""

from __future__ import annotations

import math
from collections.abc import Callable

GOLDEN = 0.5 * (3.0 - math.sqrt(5.0))  # the squared inverse of the golden ratio
SQRT_EPS = math.sqrt(2.2e-16)  # the relative resolution of an abscissa


def minimize_bounded(f: Callable[[float], float], lo: float, hi: float, xatol: float = 1e-5,
                     max_eval: int = 500) -> tuple[float, float, int]:
    """(x, f(x), evaluations): a local minimum of ``f`` in [lo, hi] to ``xatol`` (plus
    √eps·|x|). Every evaluation lies at least that far from every other."""
    if not lo < hi:
        raise ValueError(f"empty interval [{lo}, {hi}]")
    a, b = float(lo), float(hi)
    x = w = v = a + GOLDEN * (b - a)  # x: best so far, w: second best, v: the one before
    fx = fw = fv = float(f(x))
    d = e = 0.0  # the last step and the one before
    evals = 1
    while True:
        xm = 0.5 * (a + b)
        tol1 = SQRT_EPS * abs(x) + xatol / 3.0
        tol2 = 2.0 * tol1
        if abs(x - xm) <= tol2 - 0.5 * (b - a):
            return x, fx, evals
        golden = True
        if abs(e) > tol1:  # try a parabola through x, w, v
            r = (x - w) * (fx - fv)
            q = (x - v) * (fx - fw)
            p = (x - v) * q - (x - w) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            e_prev, e = e, d
            # accepted when it falls inside (a, b) and moves less than half the step before last
            if abs(p) < abs(0.5 * q * e_prev) and q * (a - x) < p < q * (b - x):
                golden = False
                d = (p + 0.0) / q
                u = x + d
                if u - a < tol2 or b - u < tol2:  # not closer than tol1 to an end
                    d = tol1 if xm - x >= 0.0 else -tol1
        if golden:
            e = (a - x) if x >= xm else (b - x)
            d = GOLDEN * e
        u = x + (d if abs(d) >= tol1 else (tol1 if d >= 0.0 else -tol1))
        fu = float(f(u))
        evals += 1
        if fu <= fx:
            if u >= x:
                a = x
            else:
                b = x
            v, fv, w, fw, x, fx = w, fw, x, fx, u, fu
        else:
            if u < x:
                a = u
            else:
                b = u
            if fu <= fw or w == x:
                v, fv, w, fw = w, fw, u, fu
            elif fu <= fv or v in (x, w):
                v, fv = u, fu
        if evals >= max_eval:
            return x, fx, evals


RTOL_ROOT = 4.0 * 2.220446049250313e-16  # the smallest relative tolerance scipy's brentq takes


def find_root(f: Callable[[float], float], a: float, b: float, xtol: float = 2e-12,
              rtol: float = RTOL_ROOT, max_iter: int = 100) -> float:
    """A zero of ``f`` in [a, b], where f(a) and f(b) differ in sign, to ``xtol + rtol·|x|``:
    Brent's zeroin (ch. 4 of the book above) in the form scipy's ``brentq`` implements —
    bisection, secant or inverse quadratic steps — so the same iterates and root to the last
    bit (tests/test_brent.py). ValueError when the signs agree or f is NaN; RuntimeError when
    ``max_iter`` steps do not converge."""
    def value(x: float) -> float:
        y = float(f(x))
        if math.isnan(y):
            raise ValueError(f"the function is NaN at {x!r}")
        return y

    xpre, xcur = float(a), float(b)
    fpre, fcur = value(xpre), value(xcur)
    if fpre * fcur > 0:
        raise ValueError("f(a) and f(b) must have different signs")
    if fpre == 0:
        return xpre
    if fcur == 0:
        return xcur
    xblk = fblk = spre = scur = 0.0  # xblk: the end that brackets the root with xcur
    for _ in range(max_iter):
        if fpre * fcur < 0:
            xblk, fblk = xpre, fpre
            spre = scur = xcur - xpre
        if abs(fblk) < abs(fcur):  # keep the better estimate in xcur
            xpre, xcur, xblk = xcur, xblk, xcur
            fpre, fcur, fblk = fcur, fblk, fcur
        delta = (xtol + rtol * abs(xcur)) / 2
        sbis = (xblk - xcur) / 2
        if fcur == 0 or abs(sbis) < delta:
            return xcur
        if abs(spre) > delta and abs(fcur) < abs(fpre):
            if xpre == xblk:  # secant through the bracket
                stry = -fcur * (xcur - xpre) / (fcur - fpre)
            else:  # inverse quadratic through the last three
                dpre = (fpre - fcur) / (xpre - xcur)
                dblk = (fblk - fcur) / (xblk - xcur)
                stry = -fcur * (fblk * dblk - fpre * dpre) / (dblk * dpre * (fblk - fpre))
            if 2 * abs(stry) < min(abs(spre), 3 * abs(sbis) - delta):  # a good short step
                spre, scur = scur, stry
            else:
                spre = scur = sbis
        else:
            spre = scur = sbis
        xpre, fpre = xcur, fcur
        xcur += scur if abs(scur) > delta else (delta if sbis > 0 else -delta)
        fcur = value(xcur)
    raise RuntimeError(f"no root to {xtol:g} in {max_iter} iterations")
