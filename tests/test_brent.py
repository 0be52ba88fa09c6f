"""identification/brent.py takes scipy's bounded Brent steps: the same minimum to the last bit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from identification.brent import find_root, minimize_bounded


def _functions() -> list[tuple[str, object, float, float]]:
    rng = np.random.default_rng(3)
    out = [
        ("quadratic", lambda x: (x - 0.3) ** 2, -1.0, 2.0),
        ("minimum at the lower end", lambda x: x, 0.5, 3.0),
        ("minimum at the upper end", lambda x: -x, 0.5, 3.0),
        ("flat", lambda x: 1.0, -2.0, 5.0),
        ("two minima", lambda x: math.sin(3.0 * x) + 0.1 * x, -3.0, 3.0),
        ("kink", lambda x: abs(x - 1.234567), 0.0, 4.0),
        ("log tau like a BIC profile", lambda x: 50.0 * math.log1p(((x - 6.3) / 1.7) ** 2)
         - 3.0 * x, math.log(60.0), math.log(7200.0)),
    ]
    for k in range(12):
        c = rng.normal(size=5)
        lo, hi = sorted(rng.uniform(-4, 4, 2))
        out.append((f"random quartic {k}", lambda x, c=c: float(np.polyval(c, x))
                    + 1e-9 * math.sin(1e3 * x), lo, hi))
    return out


@pytest.mark.parametrize("xatol", [1e-3, 1e-5, 1e-8])
def test_same_steps_as_scipy(xatol):
    for name, f, lo, hi in _functions():
        ref = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": xatol})
        x, fx, n = minimize_bounded(f, lo, hi, xatol=xatol)
        assert (x, fx, n) == (float(ref.x), float(ref.fun), int(ref.nfev)), name


def test_an_empty_interval_is_refused():
    with pytest.raises(ValueError, match="empty interval"):
        minimize_bounded(lambda x: x, 1.0, 1.0)


def _roots() -> list[tuple[str, object, float, float]]:
    rng = np.random.default_rng(5)
    out = [
        ("linear", lambda x: 2.0 * x - 1.0, 0.0, 3.0),
        ("cubic", lambda x: x**3 - 2.0 * x - 5.0, 2.0, 3.0),
        ("root at an end", lambda x: x - 1.0, 1.0, 4.0),
        ("steep", lambda x: math.expm1(20.0 * (x - 0.37)), 0.0, 1.0),
        ("flat near the root", lambda x: (x - 0.8) ** 5, 0.0, 3.0),
        ("a likelihood rise minus χ²₁(95 %)", lambda s: 14 * (math.log(s / 0.6) + 0.36 / s**2
                                                              - 1.0) - 3.841, 0.6, 4.0),
    ]
    for k in range(12):
        r = rng.uniform(-3, 3)
        c = rng.normal(size=3)
        out.append((f"random {k}", lambda x, r=r, c=c: (x - r) * (1.5 + math.tanh(
            float(np.polyval(c, x)))), r - rng.uniform(0.1, 3), r + rng.uniform(0.1, 3)))
    return out


@pytest.mark.parametrize("xtol", [2e-12, 1e-3, 1e-6])
def test_same_root_as_scipy_brentq(xtol):
    from scipy.optimize import brentq

    for name, f, lo, hi in _roots():
        calls: list[float] = []
        try:
            ref, info = brentq(f, lo, hi, xtol=xtol, full_output=True)
        except RuntimeError:  # not converged in 100 iterations: neither may this one
            with pytest.raises(RuntimeError, match="no root"):
                find_root(f, lo, hi, xtol=xtol)
            continue
        x = find_root(lambda v, f=f, calls=calls: calls.append(v) or f(v), lo, hi, xtol=xtol)
        assert x == ref and len(calls) == info.function_calls, name


def test_a_root_not_bracketed_or_nan_is_refused():
    with pytest.raises(ValueError, match="different signs"):
        find_root(lambda x: x * x + 1.0, -1.0, 1.0)
    with pytest.raises(ValueError, match="NaN"):
        find_root(lambda x: math.nan if x > 0.5 else x - 1.0, 0.0, 2.0)
