"""Sphere fit of the five stylus-centre points: exactness, health figures, noise propagation."""

import numpy as np
import pytest

from contracts.messages import TOUCH_DIRECTIONS
from identification.spherefit import SphereFitError, fit_spheres

DIRS = np.array(list(TOUCH_DIRECTIONS.values()))


def _pattern(centres: np.ndarray, radius: float) -> np.ndarray:
    return centres[:, None, :] - DIRS[None, :, :] * radius


def test_exact_five_point_pattern_free_and_fixed() -> None:
    rng = np.random.default_rng(3)
    c = rng.uniform(-300, 300, (50, 3))
    pts = _pattern(c, 15.7)
    for fixed in (False, True):
        f = fit_spheres(pts, 15.7, fixed_radius=fixed)
        assert np.abs(f.centre_mm - c).max() < 1e-9
        assert np.abs(f.radius_dev_um).max() < 1e-6
        assert f.form_rms_um.max() < 1e-6


def test_radius_deviation_is_reported_in_um() -> None:
    c = np.array([[10.0, -20.0, 30.0]])
    f = fit_spheres(_pattern(c, 15.71), 15.7)  # ball 10 µm too large (or dirt on it)
    assert f.radius_dev_um[0] == pytest.approx(10.0, abs=1e-6)
    assert np.abs(f.centre_mm - c).max() < 1e-9
    # Fixed radius: the centre shifts along the pole and the form residual shows the misfit.
    g = fit_spheres(_pattern(c, 15.71), 15.7, fixed_radius=True)
    assert g.radius_dev_um[0] == 0.0
    assert g.form_rms_um[0] > 1.0


def test_general_points_many_per_group() -> None:
    rng = np.random.default_rng(4)
    u = rng.normal(size=(20, 30, 3))
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    c = rng.uniform(-50, 50, (20, 3))
    r = rng.uniform(5, 20, 20)
    f = fit_spheres(c[:, None] + u * r[:, None, None], r)
    assert np.abs(f.centre_mm - c).max() < 1e-9
    assert np.abs(f.radius_mm - r).max() < 1e-9


def test_noise_propagation_matches_the_design() -> None:
    # Touch scatter σ along each direction → centre std σ/√2 (x, y), σ√1.25 (z)
    # (simulators/exact_log.py).
    rng = np.random.default_rng(5)
    n, s = 20000, 1e-3
    c = np.zeros((n, 3))
    pts = c[:, None] - DIRS[None] * (15.7 + rng.normal(0, s, (n, 5)))[..., None]
    f = fit_spheres(pts, 15.7)
    std = f.centre_mm.std(axis=0) / s
    assert std == pytest.approx([2**-0.5, 2**-0.5, 1.25**0.5], rel=0.03)


def test_degenerate_or_too_few_points() -> None:
    line = np.zeros((1, 5, 3))
    line[0, :, 0] = np.arange(5.0)
    with pytest.raises(SphereFitError, match="degenerate"):
        fit_spheres(line, 1.0)
    with pytest.raises(SphereFitError, match="at least 4"):
        fit_spheres(np.zeros((1, 3, 3)), 1.0)


@pytest.mark.parametrize(("scale", "reason"), [(1e308, "too large"), (1e200, "too large"),
                                               (np.inf, "not finite"), (np.nan, "not finite")])
def test_huge_or_non_finite_points_name_their_group(scale, reason) -> None:
    pts = _pattern(np.zeros((3, 3)), 15.0)
    with np.errstate(all="ignore"):
        pts[1] = DIRS * scale  # |components| ≤ 1: finite for 1e308
    with pytest.raises(SphereFitError, match=reason) as e:
        fit_spheres(pts, 15.0)
    assert e.value.groups == [1] and reason in e.value.reason


@pytest.mark.parametrize("shape", ["identical", "collinear", "coplanar"])
@pytest.mark.parametrize("fixed", [False, True])
def test_degenerate_groups_are_named(shape, fixed) -> None:
    pts = _pattern(np.zeros((4, 3)), 15.0)
    k = np.arange(5.0)[:, None]
    pts[2] = {"identical": np.full((5, 3), 7.0), "collinear": k * [1.0, 2.0, 3.0],
              "coplanar": np.concatenate([pts[2][:, :2], np.zeros((5, 1))], axis=1)}[shape]
    try:
        fit = fit_spheres(pts, 15.0, fixed_radius=fixed)
    except SphereFitError as e:
        assert e.groups == [2] and "degenerate" in e.reason
    else:  # a fixed-radius fit can place a sphere on coplanar points; then it is finite
        assert fixed and shape == "coplanar" and np.isfinite(fit.centre_mm).all()

