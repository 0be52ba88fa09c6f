"""identification.tails gives scipy.stats' f.sf, t.sf and chi2.sf without importing scipy: the
same numbers within 1e-8 relative over a grid of statistics and degrees of freedom, edges
included (0, below the support, ±∞, NaN, degrees of freedom ≤ 0), and scipy's own answer when a
continued fraction does not converge."""

from __future__ import annotations

import itertools
import math
import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

import identification.tails as tails
from identification.tails import chi2_sf, f_sf, t_sf

XS = [-math.inf, -3.0, -1e-300, 0.0, 1e-300, 1e-8, 0.3, 1.0, 2.5, 7.0, 40.0, 1e6, math.inf,
      math.nan]
DFS = [-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 7.5, 13.0, 120.0, 1e5, math.nan]

# The continued fractions converge to 1e-16 per factor; what is left is the log-gamma prefactor,
# lgamma(a + b) − lgamma(a) − lgamma(b) + a ln x + b ln y, whose terms reach ~1e7 for degrees of
# freedom near 1e6: a few 1e-9 relative (5e-9 measured over 30 000 random draws). Below 1e-250
# scipy's Cephes underflows to 0 earlier than these expansions do; there both are "0".
RTOL = 1e-8
FLOOR = 1e-250


def _close(a: float, b: float, what: tuple) -> None:
    if math.isnan(b):
        assert math.isnan(a), what
    elif abs(b) < FLOOR:
        assert abs(a) < FLOOR, (what, a, b)
    else:
        assert abs(a - b) <= RTOL * abs(b), (what, a, b)


def test_f_sf_is_scipy_stats():
    for x, d1, d2 in itertools.product(XS, DFS, DFS):
        _close(f_sf(x, d1, d2), stats.f.sf(x, d1, d2), (x, d1, d2))


def test_t_sf_is_scipy_stats():
    for x, df in itertools.product(XS, DFS):
        _close(t_sf(x, df), stats.t.sf(x, df), (x, df))


def test_chi2_sf_is_scipy_stats():
    for x, df in itertools.product(XS, DFS):
        _close(chi2_sf(x, df), stats.chi2.sf(x, df), (x, df))


def test_random_statistics_and_degrees_of_freedom_up_to_a_million():
    rng = np.random.default_rng(7)
    for _ in range(3000):
        x = float(np.exp(rng.uniform(-12, 6)))
        d1, d2 = (float(np.exp(rng.uniform(-1, 13.8))) for _ in range(2))
        sign = float(rng.choice([-1.0, 1.0]))
        _close(f_sf(x, d1, d2), stats.f.sf(x, d1, d2), ("F", x, d1, d2))
        _close(t_sf(sign * x, d1), stats.t.sf(sign * x, d1), ("t", sign * x, d1))
        _close(chi2_sf(x * d1, d1), stats.chi2.sf(x * d1, d1), ("chi2", x * d1, d1))


def test_integer_degrees_of_freedom_as_the_callers_pass_them():
    for x, n in itertools.product([0.0, 0.7, 3.2], [1, 4, 27]):
        _close(f_sf(x, n, 2 * n), stats.f.sf(x, n, 2 * n), (x, n))
        _close(t_sf(x, n), stats.t.sf(x, n), (x, n))
        _close(chi2_sf(x, n), stats.chi2.sf(x, n), (x, n))


def test_an_expansion_that_does_not_converge_hands_over_to_scipy(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(tails, "_MAX_TERMS", 2)  # no expansion converges in one term here
    assert f_sf(2.5, 7.5, 13.0) == stats.f.sf(2.5, 7.5, 13.0)
    assert t_sf(-1.0, 3.0) == stats.t.sf(-1.0, 3.0)
    assert chi2_sf(40.0, 13.0) == stats.chi2.sf(40.0, 13.0)


def test_no_scipy_import():
    code = ("import sys; from identification.tails import f_sf, t_sf, chi2_sf; "
            "f_sf(2.5, 3, 40); t_sf(1.7, 12); chi2_sf(9.0, 4); "
            "print(sorted(m for m in sys.modules if m.startswith('scipy')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"
