"""Drift-aware identification (identification/drift.py): a TCP warm-up during the run
fitted with the links where the timing separates it, chosen by BIC, the links then unbiased."""

from __future__ import annotations

import numpy as np
import pytest

from identification.drift import (
    DriftModel,
    estimate_drift_aware,
    separation,
    shape_values,
)
from identification.estimate import estimate
from identification.identifiability import nominal_centres
from identification.model import Centres, Layout, predict
from simulators.exact_log import THESIS_LINKS_UM_URAD, true_centres
from tests.drift_helpers import SIGMA, shift_visits, thesis_truth


@pytest.fixture(scope="module")
def shift():
    """The shift plan's estimate visits at the times of its run (tests/drift_helpers.py), the
    true centres of the thesis links."""
    sv = shift_visits()
    xyz = true_centres(sv.machine, sv.artefact, sv.visits, thesis_truth()).reshape(-1, 3)
    bc = np.repeat(np.array(sv.visits), len(sv.artefact.balls), axis=0)
    return sv.machine, sv.artefact, sv.pose, sv.ball, bc, xyz, sv.t_s


def _centres(shift, seed: int, warmup_um: float, tau_s: float = 900.0) -> Centres:
    _, _, pose, ball, bc, xyz, t = shift
    rng = np.random.default_rng(seed)
    f = shape_values("exponential", t, tau_s)
    drift = np.zeros_like(xyz)
    drift[:, 2] = warmup_um * 1e-3 * f
    return Centres(pose, ball, bc[:, 0], bc[:, 1],
                   xyz + rng.normal(size=xyz.shape) * SIGMA * 1e-3 + drift, t)


def _covered(est) -> float:
    """Share of the links within 2u of the truth."""
    ok = [abs(v - THESIS_LINKS_UM_URAD[k]) <= 2 * u for k, (v, u, _) in est.links_si().items()]
    return float(np.mean(ok))


def test_no_drift_keeps_the_plain_estimate_bit_for_bit(shift):
    m, a = shift[:2]
    for seed in range(4):
        c = _centres(shift, seed, 0.0)
        out = estimate_drift_aware(m, a, c)
        assert out.status == "not_selected" and out.fit is None, out.message
        assert np.array_equal(out.estimate.p, estimate(m, a, c).p)


def test_a_warm_up_is_fitted_and_the_links_are_unbiased(shift):
    m, a = shift[:2]
    plain, aware = [], []
    for seed in range(6):
        c = _centres(shift, seed, 10.0)
        out = estimate_drift_aware(m, a, c)
        assert out.status == "selected", out.message
        v, u = out.fit.over_run_um["Z"]
        assert abs(v - 10.0) <= 2.5 * u and u < 1.0  # the drift over the run, ± its u
        assert all(abs(x) <= 3 * ux for ax, (x, ux) in out.fit.over_run_um.items() if ax != "Z")
        assert out.fit.link_inflation < 2.0
        plain.append(_covered(estimate(m, a, c)))
        aware.append(_covered(out.estimate))
    # without the drift model a 10 µm warm-up puts a link outside 2u in every run
    assert max(plain) < 1.0 and np.mean(aware) >= 0.9


def test_a_drift_found_is_estimated_on_every_separable_axis(shift):
    """BIC finds the warm-up (along Z here) and its shape; the drift is then estimated on X, Y
    and Z alike (every axis is separable in the shift plan): an axis BIC would drop for being
    small still drifts, and left out it biases the others and the links. The axes without a
    drift come out within their u of 0, and Z's estimate is the three-axis model's."""
    m, a = shift[:2]
    for seed in range(3):
        out = estimate_drift_aware(m, a, _centres(shift, seed, 8.0))
        assert out.status == "selected", out.message
        assert out.fit.model.axes == ("X", "Y", "Z"), out.fit.model
        fit = out.fit.over_run_um
        assert sorted(fit) == ["X", "Y", "Z"]
        for ax in "XY":
            v, u = fit[ax]
            assert abs(v) <= 3 * u and u > 0, (ax, v, u)
        assert fit["Z"][0] == pytest.approx(8.0, abs=3 * fit["Z"][1])


def test_the_message_states_the_drift_and_tau(shift):
    m, a = shift[:2]
    out = estimate_drift_aware(m, a, _centres(shift, 1, 20.0))
    assert out.status == "selected"
    assert "Z +" in out.message and "µm" in out.message and "links are estimated" in out.message
    d = out.fit.as_dict()
    assert d["over_run_um"]["Z"]["value"] == pytest.approx(20.0, abs=2.0)
    assert d["span_s"] == pytest.approx(223.0 * 14 / 15 + 3 * 3.7, abs=1e-3)


def test_short_runs_and_missing_times_are_not_modelled(shift):
    m, a, pose, ball, bc, xyz, t = shift
    c = Centres(pose, ball, bc[:, 0], bc[:, 1], xyz)
    assert estimate_drift_aware(m, a, c).status == "no_times"
    c = Centres(pose, ball, bc[:, 0], bc[:, 1], xyz, t * 0.1)  # 22 s
    assert estimate_drift_aware(m, a, c).status == "too_short"


def test_separability_comes_from_time_not_geometry(shift):
    # A drift common to every ball is a rigid translation of each pose's centres. Give every
    # pose a free translation (a relocalisation, the most a pose-dependent link error can do)
    # and probe all balls of a pose at one instant: the drift is a combination of those
    # translations — inseparable, whatever the geometry. Visit one pose again later: the two
    # visits share the translation but not the time, and the drift separates.
    m, a = shift[:2]
    poses = [(0.0, 0.0), (45.0, 0.0), (45.0, 30.0), (15.0, 150.0), (-15.0, 210.0)]

    def sep(visits, t_visit):
        c = nominal_centres(m, a, visits)
        lay = Layout((), len(a.balls))
        _, j = predict(m, a, lay, np.zeros(lay.size), c, jacobian=True)
        keys = sorted(set(visits))
        reloc = np.zeros((len(c), 3, 3 * len(keys)))
        for k, v in enumerate(np.repeat(visits, len(a.balls), axis=0)):
            i = keys.index(tuple(v))
            reloc[k, :, 3 * i:3 * i + 3] = np.eye(3)
        t = np.repeat(t_visit, len(a.balls))
        cols = DriftModel("linear", ("X", "Y", "Z")).columns(t)
        return separation(np.concatenate([j, reloc], axis=2), SIGMA * 1e-3, cols)

    assert np.all(sep(poses, np.arange(5) * 30.0) < 1e-6)
    assert np.all(sep([*poses, poses[0]], np.arange(6) * 30.0) > 0.2)


def test_the_links_u_carries_the_choice_among_drift_models(shift, monkeypatch):
    """BIC chooses among 14 drift models; where others come close, their link estimates
    differ from the chosen one's, and that spread (weighted by e^(−BIC/2), Burnham & Anderson
    §4.3.2) is part of the links' u: never below the chosen model's own covariance, above it
    by exactly the share. So is the spread of the drift over the run (an axis another model
    leaves out counts 0 there): the fitted drift's u² grows by its diagonal."""
    import identification.drift as drift

    m, a = shift[:2]
    seen = {}
    real = drift._selection_share

    def spy(*args):
        seen["share"] = real(*args)
        return seen["share"]

    monkeypatch.setattr(drift, "_selection_share", spy)
    grown = drift_grown = 0
    for seed in range(4):
        c = _centres(shift, seed, 6.0)
        out = estimate_drift_aware(m, a, c)
        assert out.status == "selected", out.message
        share = seen["share"]
        n = share.shape[0]
        ev = np.linalg.eigvalsh(share)
        assert np.all(ev >= -1e-12 * ev.max())  # a covariance: PSD (to rounding)
        monkeypatch.setattr(drift, "_selection_share", lambda *args, n=n: np.zeros((n, n)))
        lone = estimate_drift_aware(m, a, c)
        alone = lone.estimate
        monkeypatch.setattr(drift, "_selection_share", spy)
        k = alone.cov.shape[0]
        assert n == k + 3  # links and setup, then the drift over the run of X, Y, Z
        np.testing.assert_allclose(out.estimate.cov, alone.cov + share[:k, :k], rtol=1e-9,
                                   atol=1e-24)
        for ax, (v, u) in out.fit.over_run_um.items():
            v0, u0 = lone.fit.over_run_um[ax]
            assert v == v0  # the share widens, never moves
            assert u**2 == pytest.approx(u0**2 + share[k + "XYZ".index(ax), k + "XYZ".index(ax)],
                                         rel=1e-9)
            drift_grown += bool(u > u0 * (1 + 1e-6))
        grown += bool(np.any(np.diag(share)[:3] > 1e-4 * np.diag(alone.cov)[:3]))
    assert grown >= 1  # the competing models do move the links
    assert drift_grown >= 1  # and the drift
