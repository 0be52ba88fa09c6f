"""What a stated link uncertainty means: u of an a-posteriori σ on ν residual
degrees of freedom is the standard deviation of its Student t (GUM-S1 6.4.9.4), so ±2u covers
≥ 95 %; the judge's guard band and the compensation's expanded U use one k over that u."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import t as student

from identification.estimate import a_posteriori
from identification.uncertainty import coverage_factor, expanded_k, t_variance_factor


def test_a_posteriori_covariance_is_the_t_variance():
    cov = np.diag([4.0, 1.0])
    rw = np.full(12, 1.0)  # variance factor rw·rw / (12 − 2) = 1.2
    out, sig, dof, _ = a_posteriori(rw, 2, cov, np.ones(3), math.inf, False)
    assert dof == 10.0
    np.testing.assert_allclose(sig, np.sqrt(1.2))  # σ itself stays s, the estimate of σ
    np.testing.assert_allclose(out, cov * 1.2 * 10.0 / 8.0)  # × ν/(ν−2)
    given, _, dof_g, _ = a_posteriori(rw, 2, cov, np.ones(3), math.inf, True)
    assert dof_g == math.inf and np.array_equal(given, cov)  # a given σ: u as it was


def test_two_u_covers_95_percent_when_sigma_comes_from_the_residuals():
    """A weighted least-squares fit with 22 residual dof (the shift plans have 20-24),
    20 000 replicates: ±2u of the stated u covers ≥ 95 % (theory 95.3 %); ±2 s·√c, the
    old u, covers P(|t₂₂| ≤ 2) = 94.2 %."""
    rng = np.random.default_rng(22)
    n, p, reps = 30, 8, 20000
    x = rng.normal(size=(n, p))
    cov0 = np.linalg.inv(x.T @ x)
    beta = rng.normal(size=p)
    y = x @ beta + rng.normal(size=(reps, n)) * 0.7
    b = y @ x @ cov0
    res = y - b @ x.T
    hits_new = hits_old = 0
    for r in range(reps):
        cov, _, dof, _ = a_posteriori(res[r] / 0.7, p, cov0 * 0.49, np.ones(3), math.inf, False)
        u = np.sqrt(np.diag(cov))
        err = np.abs(b[r] - beta)
        hits_new += int(np.sum(err <= 2 * u))
        hits_old += int(np.sum(err <= 2 * u / math.sqrt(t_variance_factor(dof))))
    assert dof == n - p
    assert hits_new / (reps * p) >= 0.95
    assert hits_old / (reps * p) < 0.945  # what the estimator stated before


@pytest.mark.parametrize("nu", [3.0, 5.0, 8.33, 24.3, 200.0])
def test_one_k_for_the_stated_u(nu):
    s = 1.0
    u = s * math.sqrt(t_variance_factor(nu))
    # k·u is the t interval of s: the same band whichever way it is written
    assert coverage_factor(nu, 0.95) * u == pytest.approx(student.ppf(0.975, nu) * s)
    assert expanded_k(nu, 2.0) * u == pytest.approx(student.ppf(0.5 + 0.9545 / 2, nu) * s,
                                                    rel=1e-3)
    # ±2u covers at least the 95 % a metrologist reads into "2u", for every ν ≥ 3
    assert 2 * student.cdf(2 * u / s, nu) - 1 >= 0.95
    assert expanded_k(math.inf, 2.0) == 2.0 and coverage_factor(math.inf, 0.95) == \
        pytest.approx(1.96, abs=1e-3)


def test_almost_no_redundancy_still_gives_a_finite_u():
    # ν = 2: the t has no variance; u is then scaled so that ±2u covers 95.45 %
    f = t_variance_factor(2.0)
    assert 2 * student.cdf(2 * math.sqrt(f), 2.0) - 1 == pytest.approx(0.9545, abs=1e-4)
    with pytest.raises(ValueError, match="positive"):
        t_variance_factor(0.0)
