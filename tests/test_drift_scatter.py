"""Drift-aware links under rotary index scatter: the drift refit keeps the
visit-scatter sandwich of the plain estimate, on the residuals the drift leaves."""

from __future__ import annotations

import numpy as np
import pytest

from identification.drift import estimate_drift_aware, shape_values
from identification.estimate import estimate
from identification.estimate_scatter import visit_sandwich
from identification.model import Centres
from simulators.exact_log import THESIS_LINKS_UM_URAD, true_centres
from tests.drift_helpers import SIGMA, shift_visits, thesis_truth

INDEX_URAD = 15.0  # B and C index scatter 1σ per visit: detected by the REML test


@pytest.fixture(scope="module")
def plan_visits():
    """The shift plan's estimate visits at the times of its run (tests/drift_helpers.py)."""
    sv = shift_visits()
    return sv.machine, sv.artefact, sv.visits, sv.pose, sv.ball, sv.t_s


def _centres(pv, seed: int, warmup_um: float) -> Centres:
    """Each visit indexed with its own B/C error (every ball of it moves together), a 15-min
    warm-up along Z of ``warmup_um`` over the run, centre noise."""
    m, a, visits, pose, ball, t = pv
    rng = np.random.default_rng(seed)
    d = np.rad2deg(rng.normal(size=(len(visits), 2)) * INDEX_URAD * 1e-6)
    xyz = true_centres(m, a, [(b + db, c + dc) for (b, c), (db, dc) in zip(visits, d,
                                                                            strict=True)],
                       thesis_truth()).reshape(-1, 3)
    xyz[:, 2] += warmup_um * 1e-3 * shape_values("exponential", t, 900.0)
    bc = np.repeat(np.array(visits), len(a.balls), axis=0)
    return Centres(pose, ball, bc[:, 0], bc[:, 1],
                   xyz + rng.normal(size=xyz.shape) * SIGMA * 1e-3, t)


def test_a_warming_run_with_index_scatter_keeps_the_sandwich(plan_visits):
    """Before, the drift refit used the independent-centre covariance: on these 8 runs the
    links covered their truth within 2u in 90.6 % (error/u spread 1.15); with the sandwich on
    the drift-corrected residuals, 98.4 % (0.90)."""
    m, a = plan_visits[:2]
    ok, z = [], []
    for seed in range(8):
        out = estimate_drift_aware(m, a, _centres(plan_visits, seed, 10.0))
        assert out.status == "selected", out.message
        assert out.estimate.visit_scatter is not None, f"seed {seed}: no sandwich"
        for k, (v, u, _) in out.estimate.links_si().items():
            ok.append(abs(v - THESIS_LINKS_UM_URAD[k]) <= 2 * u)
            z.append((v - THESIS_LINKS_UM_URAD[k]) / u)
    assert np.mean(ok) >= 0.95, f"2u coverage {np.mean(ok):.3f}"
    assert np.std(z) <= 1.05, f"error/u spread {np.std(z):.3f}"


def test_a_tiny_extra_column_is_kept_not_dropped_as_rank_deficient(plan_visits):
    """A τ column is ~1e-9 of a link's: the sandwich scales it, so scaling the column by s
    scales its parameter's variance by 1/s² and leaves the links' covariance as it was."""
    m, a, *_ = plan_visits
    c = _centres(plan_visits, 3, 0.0)
    base = estimate(m, a, c)
    sig = np.asarray(base.sigma_um, float) * 1e-3
    col = np.zeros((len(c), 3, 1))
    col[:, 2, 0] = 1e-3 * shape_values("linear", c.t_s, None)
    one = visit_sandwich(m, a, base.layout, base.p, c, sig, None, None, col)
    tiny = visit_sandwich(m, a, base.layout, base.p, c, sig, None, None, col * 1e-9)
    assert one is not None and tiny is not None
    n = base.layout.size
    # (to the REML optimiser's tolerance: its components move by ~1e-5 with the scaling)
    assert np.allclose(tiny.cov[:n, :n], one.cov[:n, :n], rtol=1e-3, atol=0)
    assert tiny.cov[n, n] == pytest.approx(one.cov[n, n] * 1e18, rel=1e-3)
