"""Probe physics of the simulator: contact root-finding against independent analytic solutions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from benchmarks.rigs.sim_helpers import TABLE_B2, analytic_contact, g_true, truth_with
from contracts.messages import TOUCH_DIRECTIONS
from simulators.probe import collision, first_contact


@pytest.mark.parametrize("errors", [{}, TABLE_B2], ids=["perfect", "tableB2+setup"])
@pytest.mark.parametrize("pose", [(0.0, 0.0), (30.0, 60.0), (-45.0, 330.0)])
def test_contact_equals_analytic(errors, pose):
    truth = truth_with(errors)
    b, c = pose
    for ball in range(4):
        qn = truth.centre_ctrl(ball, b, c, nominal=True)
        rho = 12.7 + 3.0
        for k, d in TOUCH_DIRECTIONS.items():
            d = np.asarray(d)
            p0, p1 = qn - d * (rho + 2.0), qn - d * (rho - 2.0)
            ct = first_contact(truth, p0, p1, b, c, 0.0)
            assert ct is not None and ct.target == ball, (ball, k)
            want = analytic_contact(truth, p0, p1, b, c, ball)
            assert np.max(np.abs(ct.contact_ctrl - want)) < 1e-6, (ball, k)


def test_motion_errors_contact_root_is_exact():
    """With a position-dependent motion error the sampled bracket + brentq path must put the
    stylus exactly on the ball sphere (checked through kinematics directly)."""
    errs = dict(TABLE_B2, effects=[{"family": "straightness", "axis": "X",
                                    "params": {"EYX_q2": 40.0, "EYX_q3": 0.0,
                                               "EZX_q2": -30.0, "EZX_q3": 20.0}}])
    truth = truth_with(errs)
    assert truth.has_motion_errors
    b, c = 30.0, 60.0
    qn = truth.centre_ctrl(0, b, c, nominal=True)
    d = np.asarray(TOUCH_DIRECTIONS[1])
    p0, p1 = qn - d * 17.7, qn - d * 13.7
    ct = first_contact(truth, p0, p1, b, c, 0.0)
    dist = np.linalg.norm(g_true(truth, ct.contact_ctrl[None], b, c, 0)[0])
    assert abs(dist - 15.7) < 1e-9

    def f(s: float) -> float:
        q = (p0 + s * (p1 - p0))[None]
        return float(np.linalg.norm(g_true(truth, q, b, c, 0)[0]) - 15.7)

    s_ref = brentq(f, 0.0, 1.0, xtol=1e-14)
    assert np.max(np.abs(ct.contact_ctrl - (p0 + s_ref * (p1 - p0)))) < 1e-6
    # And the straightness really moved the contact (the effect is not silently dropped).
    plain = first_contact(truth_with(TABLE_B2), p0, p1, b, c, 0.0)
    assert np.max(np.abs(plain.contact_ctrl - ct.contact_ctrl)) > 1e-4


def test_absent_ball_and_displaced_ball_do_not_trigger():
    truth = truth_with({"absent_balls": ["B2"]})
    qn = truth.centre_ctrl(1, 0, 0, nominal=True)
    d = np.asarray(TOUCH_DIRECTIONS[2])
    assert first_contact(truth, qn - d * 17.7, qn - d * 13.7, 0, 0, 0.0) is None
    # B1 displaced by 3 mm away from the approach: beyond 2 mm overtravel → no contact.
    far = truth_with({"setup": {"balls_um": {"B1": [3000 * 0.7071, 3000 * 0.7071, 0]}}})
    qn = far.centre_ctrl(0, 0, 0, nominal=True)
    d = np.asarray(TOUCH_DIRECTIONS[1])
    assert first_contact(far, qn - d * 17.7, qn - d * 13.7, 0, 0, 0.0) is None


def test_obstacle_triggers_early():
    truth0 = truth_with({})
    qn = truth0.centre_ctrl(0, 0, 0, nominal=True)
    d = np.asarray(TOUCH_DIRECTIONS[1])
    # A 0.5 mm chip sitting on the approach line, 1 mm outside the expected contact.
    chip_w = np.asarray(truth0.artefact.balls[0].position_mm) + np.array([-1, -1, 0]) / np.sqrt(
        2) * (12.7 + 1.0 + 0.5)
    truth = truth_with({"obstacles": [{"name": "chip", "centre_mm": chip_w.tolist(),
                                       "radius_mm": 0.5}]})
    ct = first_contact(truth, qn - d * 17.7, qn - d * 13.7, 0, 0, 0.0)
    assert ct is not None and ct.target == -1
    assert ct.s < 0.5 - 0.2  # well before the ball


def test_collision_detects_stylus_through_ball_but_not_clear_moves():
    truth = truth_with({})
    qn = truth.centre_ctrl(0, 0, 0, nominal=True)
    far = np.r_[qn + np.array([0, 0, 60.0]), 0, 0]
    assert collision(truth, far, np.r_[qn + np.array([0, 0, 20.0]), 0, 0], 0.0) is None
    assert "ball B1" in collision(truth, far, np.r_[qn, 0, 0], 0.0)
