"""identification.tails gives scipy.stats' f.sf, t.sf and chi2.sf without importing it: the
same numbers over a grid of statistics and degrees of freedom, edges included (0, below the
support, ±∞, NaN, degrees of freedom ≤ 0)."""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy import stats

from identification.tails import chi2_sf, f_sf, t_sf

XS = [-math.inf, -3.0, -1e-300, 0.0, 1e-300, 1e-8, 0.3, 1.0, 2.5, 7.0, 40.0, 1e6, math.inf,
      math.nan]
DFS = [-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 7.5, 13.0, 120.0, 1e5, math.nan]


def _same(a: float, b: float) -> None:
    # the same special function on the same arguments: equal to the last bit, NaN as NaN
    np.testing.assert_array_equal(np.float64(a), np.float64(b))


def test_f_sf_is_scipy_stats():
    for x, d1, d2 in itertools.product(XS, DFS, DFS):
        _same(f_sf(x, d1, d2), stats.f.sf(x, d1, d2))


def test_t_sf_is_scipy_stats():
    for x, df in itertools.product(XS, DFS):
        _same(t_sf(x, df), stats.t.sf(x, df))


def test_chi2_sf_is_scipy_stats():
    for x, df in itertools.product(XS, DFS):
        _same(chi2_sf(x, df), stats.chi2.sf(x, df))


def test_integer_degrees_of_freedom_as_the_callers_pass_them():
    for x, n in itertools.product([0.0, 0.7, 3.2], [1, 4, 27]):
        _same(f_sf(x, n, 2 * n), stats.f.sf(x, n, 2 * n))
        _same(t_sf(x, n), stats.t.sf(x, n))
        _same(chi2_sf(x, n), stats.chi2.sf(x, n))
