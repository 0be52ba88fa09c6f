"""Ball centres fitted in the frame the estimate corrects: each visit's five touches mapped by the
chain to the true displacement of stylus and ball, fitted there, the centre mapped back (METHOD.md
§7, "the sphere fit is not innocent").

Why. The touches latch the controller's X Y Z; the stylus lies on the ball where the true relative
displacement of stylus and ball has length R. On a machine whose axes are not square (or whose
axes have motion errors) controller coordinates are a sheared copy of that frame: the touches lie
on an ellipsoid, and a sphere fitted in controller coordinates puts its centre off the point the
chain predicts, by an amount that depends on the pose — on the fork head, whose touches follow
the tilted tool, up to 0.5 µm at 40 µrad of squareness, 3 µm at 300 µrad. The chain is affine in the
linear joints at a visit (exactly so without motion errors, to second order over a ball's 15 mm
with them), so with A = d(tip − ball)/d(controller X Y Z) the mapped touches A(q_i − q̄) lie on a
sphere of radius R whose centre maps back, through A⁻¹, to the controller position the chain
predicts: the fit is unbiased, and radius and form residual are those of the true ball.

Iterated, not at touch level. A touch-level estimate (five radial residuals and a radius per
visit in every Gauss-Newton step, the drift model and the index-scatter sandwich rebuilt on them)
would replace the centre-level estimator everything downstream rests on, for the same fixed
point. The map needs only the estimate's squareness (and held links, and scale) and the centres
depend on it weakly: up to ~13 nm per µrad of squareness on the fork head, so a map from an
estimate whose squareness is off by δ leaves ~13 nm/µrad × δ, and each pass shrinks the error
about 60 times (measured: the largest centre change 2.3 µm, 0.037, 0.0007 µm over three passes
at 300 µrad). Hence plain estimates (no drift model, no sandwich: they move the squareness by a
fraction of u, the centres by nanometres) alternate with refits until the centres settle, then
the caller's estimate runs once on them: one pass on a square machine, two to four on the fork
head.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from identification.estimate import DEFAULT_SIGMA_UM, estimate
from identification.kinematics import (
    ChainState,
    Machine,
    MotionErrorFn,
    rotary_columns,
    tip_minus_ball,
    to_model,
)
from identification.model import Artefact, Centres, Layout, chain_links
from identification.plausibility import implausible
from identification.spherefit import SphereFit, centre_sensitivity, fit_spheres

# The passes stop when the centres moved, weighted by their σ, by less than this in norm over
# the estimation centres: by Cauchy-Schwarz on the weighted least-squares solution no link
# then moves by more than 0.01u.
MOVED_TOL = 0.01
SIGMA_FLOOR_UM = 0.1  # σ used for that weighting at least (a noise-free run's is ~0)
MAX_PASSES = 5


def axis_maps(machine: Machine, layout: Layout, p: np.ndarray, centres: Centres,
              q_mm: np.ndarray, motion: Mapping[str, MotionErrorFn] | None = None
              ) -> np.ndarray:
    """(G, 3, 3) d(tip − ball)/d(controller X Y Z) at ``q_mm``: how the chain with parameters
    ``p`` maps a controller displacement to a relative displacement of stylus and ball. Affine
    in the linear joints without motion errors, so a 1 mm step is exact."""
    links, _, tip, scale = layout.unpack(p)
    state = ChainState(chain_links(machine, links), tip, scale, dict(motion or {}))
    rot = to_model(machine, rotary_columns(machine, centres.b_deg, centres.c_deg))
    ball = np.zeros((len(centres), 3))

    def g(q: np.ndarray) -> np.ndarray:
        qm = to_model(machine, {k: q[:, i] for i, k in enumerate("XYZ")}, scale)
        return tip_minus_ball(machine, {**qm, **rot}, ball, state)

    g0 = g(q_mm)
    out = np.empty((len(centres), 3, 3))
    for k in range(3):
        dq = q_mm.copy()
        dq[:, k] += 1.0
        out[:, :, k] = g(dq) - g0
    return out


def visit_maps(machine: Machine, layout: Layout, p: np.ndarray, centres: Centres
               ) -> np.ndarray:
    """(G, 3, 3) the axis map of each visit, at its measured centre: the map does not depend on
    the position without motion errors, and with them varies over millimetres, not over the
    micrometres between the measured and the predicted centre."""
    return axis_maps(machine, layout, p, centres, np.asarray(centres.xyz_mm, float))


@dataclass(frozen=True)
class FrameFit:
    """Sphere fits in the mapped frame, results in controller coordinates (G groups)."""

    fit: SphereFit  # centre_mm in controller X Y Z; radius, its deviation, form: true frame
    sens: np.ndarray  # (G, n, 3, 3) ∂centre/∂touch point, controller frame (sums to I)


def fit_in_frame(points_mm: np.ndarray, nominal_radius_mm: np.ndarray | float,
                 maps: np.ndarray | None = None, fixed_radius: bool = False) -> FrameFit:
    """Fit each group's touches (G, n, 3) after mapping them by ``maps`` (G, 3, 3) about their
    mean; None: in controller coordinates. The centre is mapped back: c = q̄ + A⁻¹ c_A, and
    ∂c/∂q_i = A⁻¹ S_i A with S_i the mapped fit's sensitivity (the mean's share cancels, as
    Σ S_i = I). ``SphereFitError`` as ``fit_spheres``."""
    pts = np.asarray(points_mm, float)
    if maps is None:
        fit = fit_spheres(pts, nominal_radius_mm, fixed_radius=fixed_radius)
        return FrameFit(fit, centre_sensitivity(pts, fit.centre_mm, fixed_radius))
    mean = pts.mean(axis=1, keepdims=True)
    mapped = np.einsum("gij,gnj->gni", maps, pts - mean)
    fit = fit_spheres(mapped, nominal_radius_mm, fixed_radius=fixed_radius)
    inv = np.linalg.inv(maps)
    centre = mean[:, 0, :] + np.einsum("gij,gj->gi", inv, fit.centre_mm)
    s = centre_sensitivity(mapped, fit.centre_mm, fixed_radius)
    sens = np.einsum("gij,gnjk,gkl->gnil", inv, s, maps)
    return FrameFit(replace(fit, centre_mm=centre), sens)


def refit(machine: Machine, layout: Layout, p: np.ndarray, centres: Centres,
          points_mm: np.ndarray, nominal_radius_mm: np.ndarray, fixed_radius: bool = False
          ) -> tuple[Centres, FrameFit]:
    """``centres`` fitted again from their touches in the frame the parameters ``p`` correct:
    centres and touch sensitivities replaced, everything else kept."""
    ff = fit_in_frame(points_mm, nominal_radius_mm, visit_maps(machine, layout, p, centres),
                      fixed_radius)
    return replace(centres, xyz_mm=ff.fit.centre_mm, touch_sens=ff.sens), ff


@dataclass(frozen=True)
class FrameEstimate:
    """The parameters whose frame the centres were fitted in, and how the passes went."""

    layout: Layout | None  # None: the fits stay in controller coordinates (see ``note``)
    p: np.ndarray
    passes: int
    moved: float  # σ-weighted norm of the last pass' centre change (``MOVED_TOL``)
    shift_um: float  # largest centre change from the controller-frame fit, µm
    note: str = ""


def frame_estimate(machine: Machine, artefact: Artefact, centres: Centres,
                   points_mm: np.ndarray, nominal_radius_mm: np.ndarray,
                   estimation: np.ndarray, links: Sequence[str] | None = None, *,
                   sigma_um: float | Sequence[float] | None = None,
                   fixed_radius: bool = False, use_distances: bool = True) -> FrameEstimate:
    """Alternate plain estimates on the ``estimation`` centres (a mask) with refits of every
    centre in their frame until the centres settle (module docstring). ``centres``: the
    controller-frame fits of ``points_mm``. An estimate the declared geometry cannot have
    (``identification.plausibility``: a wrong machine file) leaves the fits in controller
    coordinates, so the caller's own estimate is refused as before. Raises what ``estimate``
    raises."""
    mask = np.asarray(estimation, bool)
    cur = centres
    moved, passes = np.inf, 0
    est = None
    while passes < MAX_PASSES and moved >= MOVED_TOL:
        # one Gauss-Newton solve: without a stated σ, ``estimate`` would solve twice to weight
        # the axes by their own residuals, which moves the squareness by a fraction of u
        est = estimate(machine, artefact, cur.subset(mask), links,
                       sigma_um=DEFAULT_SIGMA_UM if sigma_um is None else sigma_um,
                       use_distances=use_distances, visit_scatter=False)
        if implausible(machine, artefact, est):
            return FrameEstimate(None, est.p, passes, np.inf, 0.0,
                                 "the estimate is implausible: fits left in controller axes")
        new, _ = refit(machine, est.layout, est.p, centres, points_mm, nominal_radius_mm,
                       fixed_radius)
        sig_um = (np.sqrt(np.mean(est.residual_mm**2, axis=0)) * 1e3 if sigma_um is None
                  else np.broadcast_to(np.asarray(sigma_um, float), (3,)))
        sig_mm = np.maximum(sig_um, SIGMA_FLOOR_UM) * 1e-3
        moved = float(np.linalg.norm((new.xyz_mm - cur.xyz_mm)[mask] / sig_mm))
        cur, passes = new, passes + 1
    assert est is not None
    shift = float(np.max(np.linalg.norm(cur.xyz_mm - centres.xyz_mm, axis=1)) * 1e3)
    note = "" if moved < MOVED_TOL else (f"the centres still moved by {moved:.3g} σ after "
                                         f"{passes} passes")
    return FrameEstimate(est.layout, est.p, passes, moved, shift, note)
