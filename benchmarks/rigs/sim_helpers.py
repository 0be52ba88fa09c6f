"""Simulator truth with given errors, Table B.2 errors, and analytic probe contacts."""

from __future__ import annotations

import numpy as np

from identification.kinematics import rotary_columns, tip_minus_ball, to_model
from simulators.errors_schema import errors_from_dict
from simulators.truth import TruthModel

ROOT = "config"


def truth_with(errors: dict) -> TruthModel:
    from contracts.setup_files import load_artefact, load_machine

    m, mf = load_machine(f"{ROOT}/machines/thesis_wcbxfzyt.yaml")
    a = load_artefact(f"{ROOT}/artefacts/thesis_4ball.yaml")
    return TruthModel.build(m, mf, a, errors_from_dict(errors))


TABLE_B2 = {"links": {"EB0Z": -12, "EA0Y": -24, "EC0Y": 17, "EC0B": -23, "EA0B": 2,
                      "EA0C": -19, "EB0C": 26, "EX0C": -106},
            "setup": {"balls_um": {"B1": [312, -184, 95], "B3": [-50, 400, 20]},
                      "probe_um": [145, -210, 380]}}


def g_true(truth: TruthModel, q_xyz: np.ndarray, b: float, c: float, ball: int,
           t_s: float = 0.0) -> np.ndarray:
    """Tip minus ball (foundation frame) straight from identification.kinematics."""
    n = q_xyz.shape[0]
    qm = to_model(truth.machine, {k: q_xyz[:, i] for i, k in enumerate("XYZ")})
    qm.update(to_model(truth.machine, rotary_columns(truth.machine, np.full(n, b),
                                                     np.full(n, c))))
    w = truth.ball_centres_mm(t_s, b, c)[ball]
    return tip_minus_ball(truth.machine, qm, np.broadcast_to(w, (n, 3)).copy(), truth.state)


_AFFINE: dict = {}


def analytic_contact(truth: TruthModel, p0, p1, b, c, ball) -> np.ndarray:
    """Affine chain: g(q) = A (q - q_c) with A by unit finite differences (exact), then the
    smaller root of |A (p0 + s (p1 - p0) - q_c)| = R + r."""
    key = (id(truth), ball, b, c)
    if key not in _AFFINE:
        qc = truth.centre_ctrl(ball, b, c)
        a = np.stack([g_true(truth, (qc + e)[None], b, c, ball)[0] for e in np.eye(3)], axis=1)
        a -= g_true(truth, qc[None], b, c, ball)[0][:, None]
        _AFFINE[key] = (truth, qc, a)  # the truth is kept so that its id stays unique
    _, qc, a = _AFFINE[key]
    rho = truth.ball_radii_mm[ball] + truth.stylus_radius_mm
    u, w = a @ (p1 - p0), a @ (p0 - qc)
    qa, qb, qcst = u @ u, 2 * u @ w, w @ w - rho**2
    s = (-qb - np.sqrt(qb * qb - 4 * qa * qcst)) / (2 * qa)
    return p0 + s * (p1 - p0)
