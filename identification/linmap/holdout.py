"""A held-out placement judged by a map: its centres predicted by the machine (links, map,
probe setup fixed) once its own ball setup is fitted (a placement's setup is always its own)."""

from __future__ import annotations

import numpy as np

from identification.kinematics import Machine
from identification.linmap.problem import JointLayout, Placement, evaluate
from identification.linmap.refit import refit_centres

GN_ITER = 10
GN_TOL_MM = 1e-9


def holdout_residual_mm(machine: Machine, placement: Placement, layout: JointLayout,
                        model_p: np.ndarray) -> np.ndarray:
    """(K, 3) measured − predicted centres of ``placement`` under the links, map and probe of
    ``model_p`` (the first ``layout.tip_slice.stop`` entries of a fit's vector), its ball
    setup fitted by Gauss-Newton (the spheres re-fitted in the estimate's frame when the
    touches are there, as the map's own placements are)."""
    lay = JointLayout(layout.links, layout.basis, (len(placement.artefact.balls),))
    p = np.zeros(lay.size)
    p[: lay.tip_slice.stop] = np.asarray(model_p, float)[: layout.tip_slice.stop]
    balls = lay.ball_slice(0)
    pl = placement
    for round_ in range(2):
        for _ in range(GN_ITER):
            ev = evaluate(machine, [pl], lay, p, jacobian=True)
            assert ev.jac is not None
            r = (pl.centres.xyz_mm - ev.pred[0]).reshape(-1)
            j = ev.jac[0].reshape(-1, lay.size)[:, balls]
            step = np.linalg.lstsq(j, r, rcond=None)[0]
            p[balls] += step
            if np.max(np.abs(step)) < GN_TOL_MM:
                break
        if round_ == 0 and pl.points_mm is not None:
            pl = refit_centres(machine, [placement], lay, p)[0]
        else:
            break
    return pl.centres.xyz_mm - evaluate(machine, [pl], lay, p).pred[0]
