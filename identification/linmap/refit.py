"""Ball centres re-fitted in the frame the current estimate corrects (METHOD.md §7).

Five touches fitted as a sphere in controller coordinates meet a sphere only on a square,
error-free machine: the links' squareness and, more, the slopes of the motion errors shear it,
and the free-radius fit of four equator touches and a one-sided pole moves the centre along the
pole by about the radius times the strain difference (measured on simulated maps: 0.2-0.5 µm sd
per centre, 1.5 µm at most; the map then carried that bias). Here each touch's latched
controller position p is carried by the current estimate (links, map, setups) into
g(p) = tip − ball in the foundation frame, where the estimated machine is rigid and the touches
lie on a round sphere; the sphere is fitted there (free or fixed radius as the centres were) and
its centre δ brought back to the controller position q with g(q) = δ (Newton). Two rounds with
the estimate make the bias second order in what the estimate misses.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from identification.kinematics import Machine
from identification.linmap.problem import JointLayout, MapError, Placement, _g, centre_jq
from identification.spherefit import SphereFitError, fit_spheres

NEWTON_STEPS = 2


def refit_centres(machine: Machine, placements: Sequence[Placement], layout: JointLayout,
                  p: np.ndarray) -> list[Placement]:
    """Every placement with touches, its centres re-fitted under the estimate ``p``."""
    motion = layout.basis.motion_errors(np.asarray(p, float)[layout.map_slice])
    out = []
    for i, pl in enumerate(placements):
        if pl.points_mm is None or pl.radius_mm is None:
            out.append(pl)
            continue
        lay, idx = layout.local(i)
        q = pl.centres.xyz_mm.copy()
        jq, state, balls_w, rot = centre_jq(machine, pl, lay, p[idx], q, motion)
        k, n = pl.points_mm.shape[:2]
        rot_n = {a: np.repeat(v, n) for a, v in rot.items()}
        g_pts = _g(machine, rot_n, np.repeat(balls_w, n, axis=0),
                   pl.points_mm.reshape(-1, 3), state).reshape(k, n, 3)
        try:
            delta = fit_spheres(g_pts, pl.radius_mm, fixed_radius=pl.fixed_radius).centre_mm
        except SphereFitError as e:  # the touches fitted in controller coordinates already
            raise MapError(f"{pl.name}: sphere fit in the estimate's frame failed: "
                           f"{e.reason}") from None
        for _ in range(NEWTON_STEPS):
            q = q + np.linalg.solve(jq, (delta - _g(machine, rot, balls_w, q, state))[..., None]
                                    )[..., 0]
        out.append(pl.with_xyz(q))
    return out
