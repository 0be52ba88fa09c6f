"""Centres without touches → the gap diagnosis' groups, and the noise floor when the touches
carry none: never a zero form residual.

A centre measured by an instrument (a centres file) is one group with three observations, its
x, y, z; there is no form residual (``Groups.channels`` = 3: the fourth observation is not
used, ``linear.py`` and ``locate.py`` count only the live ones). Effects still act through the
group operators: each centre stands for five pseudo-touches along x, y, z, x, y whose radial
change the first three map one to one onto the centre (``to_centre``), so a ball offset or a
drift of the reading moves the centre exactly as it moves a probed one, while a direction
pattern of a touch probe (pre-travel) is a constant shift the probe setup absorbs — invisible,
as it should be on centres an instrument already reduced. The probed sphere's distortion by the
axis map is zero (no touches: ``radius_mm`` 0).

Noise floor: from the stated uncertainties (the file's ``u_um`` or
``repeatability_um``, ``--repeatability-um``), else from repeats (``data.repeat_scatter_um``),
else no diagnosis: a floor is never invented. The same rule holds for touches whose form
residual is (numerically) zero — a simulation without noise: the floor comes from a stated
repeatability or from repeats, and the form residual, zero by construction, is not used.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from identification.gap.data import Groups, TouchData, repeat_scatter_um
from identification.model import Centres

EXACT_FORM_UM = 1e-3  # data.group_touches clamps its floor here: at it, the touches are exact
STATED_DOF = 1_000_000  # a stated uncertainty: as good as infinitely many degrees of freedom
_NORMALS = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0]])


def centre_touches(centres: Centres, repeat: np.ndarray) -> TouchData:
    """Five pseudo-touches per centre (rows 5k … 5k+4, along x, y, z, x, y), for the
    effects' context."""
    k = len(centres)
    rep5 = lambda a: np.repeat(np.asarray(a), 5, axis=0)  # noqa: E731
    t = centres.t_s if centres.t_s.size else np.zeros(k)
    return TouchData(repeat=rep5(repeat), pose=rep5(centres.pose), ball=rep5(centres.ball),
                     touch=np.tile(np.arange(1, 6), k), t_s=rep5(t), b_deg=rep5(centres.b_deg),
                     c_deg=rep5(centres.c_deg), direction=np.tile(_NORMALS, (k, 1)),
                     xyz_mm=rep5(centres.xyz_mm))


def _floor_from_repeats(groups: Groups, what: str) -> tuple[np.ndarray, int]:
    rep = repeat_scatter_um(groups)
    if rep is None or not np.all(rep[0] > EXACT_FORM_UM):
        why = ("their repeats agree exactly" if rep is not None else
               "no pose and ball was measured twice")
        raise ValueError(f"{what}, and {why}: there is no noise floor to judge a gap against; "
                         "state the centre repeatability (--repeatability-um, or u_um / "
                         "repeatability_um in a centres file) or measure with repeats ≥ 2")
    return rep[0], rep[1] // 3


def _with_floor(groups: Groups, sigma_um: np.ndarray, dof: int) -> Groups:
    """Groups whose centre covariance is diag(σ²) (σ per axis or per centre) and whose form
    residual is not an observation."""
    s = np.broadcast_to(np.asarray(sigma_um, float), (len(groups), 3))
    cov = np.einsum("gi,ij->gij", s**2, np.eye(3))
    return replace(groups, centre_cov_um2=cov, sigma_dof=int(dof), channels=3,
                   sigma_touch_um=float(np.sqrt(np.mean(s**2))))


def centre_groups(centres: Centres, repeat: np.ndarray,
                  sigma_um: np.ndarray | Sequence[float] | None = None,
                  is_holdout: np.ndarray | None = None) -> tuple[Groups, np.ndarray]:
    """Groups of measured centres, in time order (folds and time blocks follow the run), and
    ``is_holdout`` in that order; group j stands for the pseudo-touches 5j … 5j+4 of
    ``centre_touches(groups.centres, groups.repeat)``. ``sigma_um``: stated, (3,) per axis or
    (K, 3) per centre (in ``centres`` order); None: from repeats, else a ``ValueError``."""
    k = len(centres)
    if k == 0:
        raise ValueError("no centre to diagnose")
    order = np.argsort(centres.t_s if centres.t_s.size else np.zeros(k), kind="stable")
    ho = np.zeros(k, bool) if is_holdout is None else np.asarray(is_holdout, bool)[order]
    to_centre = np.zeros((k, 3, 5))
    to_centre[:, [0, 1, 2], [0, 1, 2]] = 1.0
    g = Groups(centres=centres.subset(order), repeat=np.asarray(repeat, int)[order],
               touch_index=np.arange(5 * k).reshape(k, 5),
               normal=np.broadcast_to(_NORMALS, (k, 5, 3)).copy(),
               radial_res_um=np.zeros((k, 5)), radius_dev_um=np.zeros(k),
               radius_mm=np.zeros(k), to_centre=to_centre, form_dir=np.zeros((k, 5)),
               form_um=np.zeros(k), sigma_touch_um=1.0, sigma_dof=STATED_DOF,
               centre_cov_um2=np.broadcast_to(np.eye(3), (k, 3, 3)).copy(), channels=3)
    if sigma_um is not None:
        s = np.asarray(sigma_um, float)
        if s.shape not in ((3,), (k, 3)) or not np.all(np.isfinite(s) & (s > 0)):
            raise ValueError(f"centre uncertainties: expected positive numbers, 3 or {k} × 3")
        return _with_floor(g, s[order] if s.ndim == 2 else s, STATED_DOF), ho
    std, dof = _floor_from_repeats(g, "these centres state no uncertainty")
    return _with_floor(g, std, dof), ho


def exact_floor(groups: Groups, repeatability_um: Sequence[float] | None) -> tuple[Groups, str]:
    """Touch groups as they are, unless their form residual is numerically zero (exact
    touches): then the stated repeatability or the repeats set the floor and the form residual
    is dropped (``ValueError`` when neither exists). Returns the groups and a note for the
    report ("" when nothing changed)."""
    if groups.sigma_touch_um > EXACT_FORM_UM:
        return groups, ""
    head = (f"touches exact (form residual ≤ {EXACT_FORM_UM} µm, a simulation without noise?): "
            "the form residual is not used and the floor is ")
    if repeatability_um is not None:
        s = np.asarray(repeatability_um, float)
        return _with_floor(groups, s, STATED_DOF), (
            head + f"the stated repeatability {'/'.join(f'{v:g}' for v in s)} µm x/y/z")
    std, dof = _floor_from_repeats(groups, "the touches are exact (zero form residual)")
    return _with_floor(groups, std, dof), (
        head + f"the scatter between repeats {'/'.join(f'{v:.3f}' for v in std)} µm x/y/z "
        f"({dof} dof)")


def merge(train: tuple[Centres, np.ndarray], holdout: tuple[Centres, np.ndarray] | None
          ) -> tuple[Centres, np.ndarray, np.ndarray]:
    """(centres, repeat, is_holdout) of a training and a hold-out set: the hold-out's pose and
    repeat numbers are its own and kept apart (as ``diagnose._merge`` does for touches)."""
    c, r = train
    if holdout is None:
        return c, np.asarray(r), np.zeros(len(c), bool)
    h, hr = holdout
    cat = Centres(np.r_[c.pose, h.pose + int(c.pose.max()) + 1], np.r_[c.ball, h.ball],
                  np.r_[c.b_deg, h.b_deg], np.r_[c.c_deg, h.c_deg],
                  np.vstack([c.xyz_mm, h.xyz_mm]),
                  np.r_[c.t_s if c.t_s.size else np.zeros(len(c)),
                        h.t_s if h.t_s.size else np.zeros(len(h))])
    rep = np.r_[r, np.asarray(hr) + int(np.max(r)) + 1]
    return cat, rep, np.r_[np.zeros(len(c), bool), np.ones(len(h), bool)]
