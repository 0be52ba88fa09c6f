"""Monte Carlo of thesis Table 4.1 and the linearisation it rests on."""

from pathlib import Path

import numpy as np
import pytest

from contracts.setup_files import load_artefact, load_machine
from identification import montecarlo as mc
from identification.estimate import estimate
from identification.model import Centres
from simulators.exact_log import Truth, true_centres

CFG = Path(__file__).resolve().parents[1] / "config"
EIGHT = ("EB0Z", "EA0Y", "EC0Y", "EA0B", "EC0B", "EX0C", "EA0C", "EB0C")


@pytest.fixture(scope="module")
def thesis():
    m, _ = load_machine(CFG / "machines/thesis_wcbxfzyt.yaml")
    return m, load_artefact(CFG / "artefacts/thesis_4ball.yaml")


def test_table_4_1_behaviour(thesis) -> None:
    m, a = thesis
    poses = mc.grid_poses((-45, 45), (0, 360), 15)
    assert len(poses) == 175
    jac, _ = mc.jacobian(m, a, poses, EIGHT)
    alone = mc.run(m, a, poses, EIGHT, simultaneous=False, jac=jac)
    both = mc.run(m, a, poses, EIGHT, simultaneous=True, jac=jac)
    # Setup alone: the BC offset leaks into the probe x setup (thesis 3.5, Table 4.1: 5.06 µm).
    assert alone.probe_um[0] > 3.0 and alone.artefact_um > 0.1
    # Simultaneous: the method contribution vanishes (≥ 2 orders of magnitude).
    assert both.artefact_um < alone.artefact_um / 100
    assert both.probe_agg_um < alone.probe_agg_um / 100
    # Widening B to ±180° lowers the setup-only uncertainty.
    wide = mc.grid_poses((-180, 180), (0, 360), 15)
    wide_alone = mc.run(m, a, wide, EIGHT, simultaneous=False)
    assert wide_alone.artefact_um < alone.artefact_um
    assert wide_alone.probe_agg_um < alone.probe_agg_um
    # Probing repeatability (thesis 3.4) over 700 centres: well below a micrometre.
    assert 0.01 < both.artefact_repeat_um < 0.2


def test_draw_statistics_match_the_analytic_propagation(thesis) -> None:
    m, a = thesis
    poses = mc.grid_poses((-45, 45), (0, 360), 45)
    jac, layout = mc.jacobian(m, a, poses, EIGHT)
    r = mc.run(m, a, poses, EIGHT, simultaneous=False, draws=10_000, jac=jac, seed=2)
    pinv, _ = mc.linear_estimator(jac, layout, False)
    sig = np.array([5e-6 if n[1] in "ABC" else 5e-3 for n in EIGHT])
    mm = pinv @ jac[:, :8] * sig
    analytic = np.sqrt(np.sum(mm**2, axis=1)) * 1e3
    np.testing.assert_allclose(r.probe_um, analytic[-3:], rtol=0.05, atol=1e-6)


def test_linearisation_against_exact_chain(thesis) -> None:
    m, a = thesis
    poses = mc.grid_poses((-45, 45), (0, 360), 45)  # 3 × 9 poses: cheap, same geometry
    jac, layout = mc.jacobian(m, a, poses, EIGHT)
    rng = np.random.default_rng(9)
    sig = np.array([5e-6 if n[1] in "ABC" else 5e-3 for n in EIGHT])
    n = len(a.balls)
    for simultaneous in (False, True):
        pinv, cols = mc.linear_estimator(jac, layout, simultaneous)
        for _ in range(3):
            e = rng.standard_normal(8) * sig
            xyz = true_centres(m, a, poses, Truth(dict(zip(EIGHT, e, strict=True))))
            pb = np.repeat(np.array(poses), n, axis=0)
            c = Centres(np.repeat(np.arange(len(poses)), n), np.tile(np.arange(n), len(poses)),
                        pb[:, 0], pb[:, 1], xyz.reshape(-1, 3))
            # The Monte Carlo is the unweighted pseudo-inverse of thesis Eq. 4.2: compare with
            # the estimator at an isotropic σ (without one it reweights per axis).
            exact = estimate(m, a, c, links=EIGHT if simultaneous else (), sigma_um=1.0)
            lin = pinv @ (jac[:, :8] @ e)
            setup_exact = exact.p[-3 * n - 3:] * 1e3
            setup_lin = lin[np.flatnonzero(cols >= 8)] * 1e3
            assert np.abs(setup_exact - setup_lin).max() < 1e-4  # µm, ≪ 0.01 µm


def test_repeatability_matches_estimator_covariance(thesis) -> None:
    m, a = thesis
    poses = mc.grid_poses((-45, 45), (0, 360), 45)
    # The Monte Carlo estimator is the unweighted pinv of thesis Eq. 4.2, i.e. the default
    # (isotropic) weighting of ``estimate``; compare with an isotropic repeatability.
    r = mc.run(m, a, poses, EIGHT, simultaneous=True, draws=10, repeatability_um=(0.8,) * 3)
    n = len(a.balls)
    pb = np.repeat(np.array(poses), n, axis=0)
    xyz = true_centres(m, a, poses, Truth())
    c = Centres(np.repeat(np.arange(len(poses)), n), np.tile(np.arange(n), len(poses)),
                pb[:, 0], pb[:, 1], xyz.reshape(-1, 3))
    e = estimate(m, a, c, links=EIGHT, sigma_um=0.8)
    np.testing.assert_allclose(e.balls_um[1], r.balls_repeat_um, rtol=1e-6)
    np.testing.assert_allclose(e.probe_um[1], r.probe_repeat_um, rtol=1e-6)
