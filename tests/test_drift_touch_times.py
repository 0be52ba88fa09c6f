"""A drift moving the ball while it is touched reaches its centre through the sphere fit (issue
22): X and Y at about the equator touches' times, Z at the pole's. The drift-aware estimate's
columns carry it touch by touch (identification/spherefit.py ``centre_sensitivity``,
identification/drift.py ``Touches``), not at the centre's mean touch time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis.touch_centres import rows_to_centres
from identification.drift import DriftFit, DriftModel, Touches, estimate_drift_aware
from identification.model import Centres
from identification.spherefit import centre_sensitivity, fit_spheres
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.errors_schema import errors_from_dict
from simulators.offline import run_sync
from simulators.truth import TruthModel

MACHINE = "config/machines/thesis_wcbxfzyt.yaml"
ARTEFACT = "config/artefacts/thesis_4ball.yaml"
PLAN = "config/plans/shift_start_14poses.yaml"


def _ball(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Four diagonal equator touches and the pole of a 12.7 mm ball (+ stylus), 1 µm noise."""
    rng = np.random.default_rng(seed)
    n = np.array([[1, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0], [0, 0, np.sqrt(2)]])
    n = n / np.sqrt(2)
    c = np.array([120.0, -35.0, 210.0])
    return (c + 12.7 * n + rng.normal(0, 1e-3, (5, 3)))[None], c


@pytest.mark.parametrize("fixed", [False, True])
def test_the_sensitivity_is_the_fits_derivative(fixed):
    pts, _ = _ball(1)
    fit = fit_spheres(pts, 12.7, fixed_radius=fixed)
    s = centre_sensitivity(pts, fit.centre_mm, fixed)
    np.testing.assert_allclose(s.sum(axis=1)[0], np.eye(3), atol=1e-9)  # a translation
    h = 1e-5
    for i in range(5):
        for a in range(3):
            q = pts.copy()
            q[0, i, a] += h
            fd = (fit_spheres(q, 12.7, fixed_radius=fixed).centre_mm - fit.centre_mm)[0] / h
            np.testing.assert_allclose(s[0, i, :, a], fd, atol=1e-3)  # GN tolerance
    if not fixed:  # the free radius: Z of the centre is the pole's, X/Y the equator's
        assert s[0, 4, 2, 2] == pytest.approx(1.0, abs=1e-3)
        assert np.abs(s[0, 4, :2, :]).max() < 1e-3
        assert s[0, :4, 0, 0].sum() == pytest.approx(1.0, abs=1e-3)


def test_columns_without_touches_are_the_centre_times():
    t = np.array([0.0, 10.0, 20.0])
    sens = np.broadcast_to(np.eye(3) / 5, (3, 5, 3, 3)).copy()
    same = Touches(np.repeat(t[:, None], 5, axis=1), sens)  # every touch at the centre's time
    for model in (DriftModel("linear", ("X", "Z")), DriftModel("exponential", ("Y",), 600.0)):
        np.testing.assert_allclose(model.columns(t, same), model.columns(t), atol=1e-15)
    c = Centres(np.zeros(3, int), np.zeros(3, int), np.zeros(3), np.zeros(3), np.zeros((3, 3)), t)
    assert Touches.of(c) is None  # an instrument's centres: their times only


@pytest.fixture(scope="module")
def warm_run():
    """The shift plan on the simulated thesis machine without noise, a 20 µm warm-up (τ 30 min)
    along (1, −1, 1)/√3 over the run."""
    m, mf = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    plan = load_plan(PLAN)
    e = yaml.safe_load(Path("config/errors/thesis_tableB2.yaml").read_text())
    e["probe"]["touch_noise_um"] = 0.0
    e["probe"]["centre_noise_um"] = [0.0, 0.0, 0.0]
    amp = 20.0 / np.sqrt(3) / -np.expm1(-223.0 / 1800.0)
    e["thermal"] = {"axes": {k: {"amplitude_um": float(s * amp), "tau_s": 1800.0}
                             for k, s in zip("XYZ", (1, -1, 1), strict=True)}}
    truth = TruthModel.build(m, mf, a, errors_from_dict(e))
    text = get_dialect("fanuc").render(build_program(m, mf, a, plan))
    res = run_sync(truth, text, "fanuc", seed=2)
    assert res.state == "done", res.alarm
    data = rows_to_centres(res.rows, a, plan.stylus_radius_mm)
    c = data.centres.subset(~np.isin(data.centres.pose, plan.indices("validate")))
    return m, a, c, {k: float(v) for k, v in truth.errors.links.items()}


def test_the_drift_aware_links_see_the_drift_touch_by_touch(warm_run):
    """Noise-free, what the fit leaves is what the model misses of the drift. Through the
    touches it misses far less than at the centres' mean touch times (measured: residual rms
    0.0045 against 0.0134 µm, τ 1801 against 1878 s for a true 1800, link error rms 0.028
    against 0.061 µm / µrad)."""
    m, a, c, want = warm_run
    assert Touches.of(c) is not None and c.touch_t_s.shape == (len(c), 5)
    assert np.ptp(c.touch_t_s, axis=1).min() > 1.0  # the touches of a ball take seconds
    blind = Centres(c.pose, c.ball, c.b_deg, c.c_deg, c.xyz_mm, c.t_s)  # times only
    got = {}
    for name, cc in (("touches", c), ("centre times", blind)):
        out = estimate_drift_aware(m, a, cc, links=list(want))
        assert out.status == "selected" and out.fit is not None, out.message
        assert out.fit.model.shape == "exponential" and out.fit.tau_s is not None
        err = [v - want[k] for k, (v, _, _) in out.estimate.links_si().items()]
        got[name] = (out.estimate.residual_rms_um, out.fit.tau_s[0],
                     float(np.sqrt(np.mean(np.square(err)))))
    (res_t, tau_t, err_t), (res_c, tau_c, err_c) = got["touches"], got["centre times"]
    assert res_t < 0.5 * res_c, got
    assert abs(tau_t - 1800.0) < 0.005 * 1800.0 < abs(tau_c - 1800.0) / 4, got
    assert err_t < 0.7 * err_c, got


def test_the_fitted_drift_is_taken_out_as_the_fit_saw_it():
    """``corrected`` centres (daemon/analysis/thermal.py) lose the fitted drift the way the fit
    modelled it: touch by touch, and on the fit's own time origin — a held-out centre probed
    before the first estimate centre must not move the origin of the others (it did)."""
    fit = DriftFit(DriftModel("linear", ("X",)), 100.0, {"X": (5.0, 0.1)}, None, None, 10.0,
                   1.0, start_t_s=10.0)
    np.testing.assert_allclose(fit.drift_mm(np.array([5.0, 10.0, 60.0, 110.0]))[:, 0] * 1e3,
                               [-0.25, 0.0, 2.5, 5.0], atol=1e-12)
    t = np.array([[8.0, 9.0, 10.0, 11.0, 14.0], [58.0, 59.0, 60.0, 61.0, 64.0]])
    pts, _ = _ball(3)
    sens = np.repeat(centre_sensitivity(pts, fit_spheres(pts, 12.7).centre_mm), 2, axis=0)
    c = Centres(np.zeros(2, int), np.zeros(2, int), np.zeros(2), np.zeros(2), np.zeros((2, 3)),
                t.mean(axis=1), t, sens)
    want = np.einsum("knab,knb->ka", sens, fit.drift_mm(t))
    np.testing.assert_allclose(fit.centre_drift_mm(c), want, atol=1e-15)
    # the equator's mean time along X (1 s before the 5-touch mean here): 0.05 µm less
    assert fit.centre_drift_mm(c)[0, 0] * 1e3 == pytest.approx(
        (np.mean(t[0, :4]) - 10.0) * 0.05, abs=2e-3)
