"""The volumetric error of the map at commanded positions, its uncertainty, the rigid-body
convention, and the comparison of two maps (METHOD.md §7).

Volumetric error at controller X, Y, Z with the rotary axes at zero: the nominal tool tip's
actual minus nominal position relative to the workpiece, in the last workpiece frame. Actual:
the chain with the controller-held and estimated links and the map's motion errors; nominal:
the chain the controller believes (held links only). The stylus' own setup offset is not part
of it (it is the tool's, a constant).

A map is defined up to a rigid-body motion (the balls' setup takes up any). Convention: the
field minus its least-squares rigid motion (translation + small rotation about the centroid)
over a regular grid of ``GRID_N``³ points spanning the covered box; the rigid part is linear
in the field, so the stated u are those of the convention's field (its rigid part carries the
setup's large uncertainty and is gone). Two maps are compared after removing the best rigid
motion of their difference over the same grid.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from identification.kinematics import ChainState, Machine, frames, to_model
from identification.linmap.columns import map_columns
from identification.linmap.terms import MapBasis
from identification.model import _link_columns, chain_links

GRID_N = 7
INSIDE_MM = 1e-6  # a point this far beyond the covered box still counts as inside


class OutsideCoverage(ValueError):
    """A point outside the covered range of an axis: the map does not extrapolate."""

    def __init__(self, index: int, axis: str, value: float, lo: float, hi: float) -> None:
        super().__init__(f"point {index + 1}: {axis} = {value:g} mm is outside the covered range "
                         f"{lo:g} .. {hi:g} mm of {axis}: the map does not extrapolate")
        self.index, self.axis = index, axis


@dataclass(frozen=True)
class MapModel:
    """What a prediction needs: the machine, the estimated links and map coefficients
    (``values``, mm / rad, links first) with their covariance, the covered box (controller
    mm per axis)."""

    machine: Machine
    links: tuple[str, ...]
    basis: MapBasis
    values: np.ndarray
    cov: np.ndarray
    box_mm: Mapping[str, tuple[float, float]]

    @property
    def size(self) -> int:
        return len(self.links) + self.basis.size

    def grid(self, n: int = GRID_N) -> np.ndarray:
        """(n³, 3) controller X Y Z on a regular grid over the covered box."""
        axes = [np.linspace(*self.box_mm[a], n) for a in "XYZ"]
        g = np.meshgrid(*axes, indexing="ij")
        return np.stack([x.ravel() for x in g], axis=1)


def box_from_ranges(machine: Machine, ranges_mm: Mapping[str, tuple[float, float]]
                    ) -> dict[str, tuple[float, float]]:
    """Covered box in controller mm from model joint ranges (the machine file's sign)."""
    out = {}
    for a, (lo, hi) in ranges_mm.items():
        s = machine.axes[a].sign
        out[a] = (min(lo * s, hi * s), max(lo * s, hi * s))
    return out


def check_inside(model: MapModel, xyz_ctrl: np.ndarray) -> None:
    """Raise ``OutsideCoverage`` for the first point outside the covered box."""
    for i, a in enumerate("XYZ"):
        lo, hi = model.box_mm[a]
        bad = np.flatnonzero((xyz_ctrl[:, i] < lo - INSIDE_MM) | (xyz_ctrl[:, i] > hi + INSIDE_MM))
        if bad.size:
            k = int(bad[0])
            raise OutsideCoverage(k, a, float(xyz_ctrl[k, i]), lo, hi)


def raw_field(model: MapModel, xyz_ctrl: np.ndarray, values: np.ndarray | None = None,
              jacobian: bool = False
              ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """(error (N, 3) mm in the workpiece frame, d(error)/d(values) (N, 3, P) or None, the
    nominal tip in the workpiece frame (N, 3) mm) at controller X Y Z, rotary axes at zero."""
    m = model.machine
    v = model.values if values is None else np.asarray(values, float)
    xyz = np.atleast_2d(np.asarray(xyz_ctrl, float))
    n = xyz.shape[0]
    q = {a: xyz[:, i] for i, a in enumerate("XYZ")}
    q.update({r: np.zeros(n) for r in m.rotary_axes})
    qm = to_model(m, q)
    tip = np.asarray(m.tool_tip_mm, float)

    def tip_w(state: ChainState) -> tuple[np.ndarray, np.ndarray]:
        f_w, f_t = frames(m, qm, state)
        t = f_t[:, :3, :3] @ tip + f_t[:, :3, 3]
        return np.einsum("sji,sj->si", f_w[:, :3, :3], t - f_w[:, :3, 3]), f_w

    nominal, _ = tip_w(ChainState(links=m.held_link_values()))
    links = dict(zip(model.links, v[: len(model.links)], strict=True))
    state = ChainState(links=chain_links(m, links),
                       motion_errors=model.basis.motion_errors(v[len(model.links):]))
    actual, f_w = tip_w(state)
    err = actual - nominal
    if not jacobian:
        return err, None, nominal
    # d(tip in W)/dp = R_Wᵀ · dg/dp, g = F_T_T·tip − F_T_W·w at w = the actual tip in W
    dg = np.concatenate([_link_columns(m, qm, state, actual, model.links),
                         map_columns(m, qm, state, actual, model.basis)], axis=2)
    jac = np.einsum("sji,sjp->sip", f_w[:, :3, :3], dg)
    return err, jac, nominal


def rigid_design(points_mm: np.ndarray, centre_mm: np.ndarray) -> np.ndarray:
    """(N, 3, 6): the displacement t + ω × (p − c) of each point per (t, ω)."""
    r = points_mm - centre_mm
    d = np.zeros((len(points_mm), 3, 6))
    d[:, :, :3] = np.eye(3)
    # ω × r = −r × ω = −[r]× ω
    d[:, 0, 4], d[:, 0, 5] = r[:, 2], -r[:, 1]
    d[:, 1, 3], d[:, 1, 5] = -r[:, 2], r[:, 0]
    d[:, 2, 3], d[:, 2, 4] = r[:, 1], -r[:, 0]
    return d


@dataclass(frozen=True)
class Prediction:
    error_um: np.ndarray  # (N, 3) under the rigid convention, workpiece frame
    u_um: np.ndarray  # (N, 3) standard uncertainty of each component
    raw_um: np.ndarray  # (N, 3) before the rigid convention
    jac: np.ndarray  # (N, 3, P) of error_um's mm per parameter unit


def predict_field(model: MapModel, xyz_ctrl: np.ndarray, check: bool = True,
                  grid_n: int = GRID_N) -> Prediction:
    """The volumetric error under the rigid convention (module docstring) with its standard
    uncertainty from the covariance; ``OutsideCoverage`` for a point outside the box."""
    xyz = np.atleast_2d(np.asarray(xyz_ctrl, float))
    if check:
        check_inside(model, xyz)
    e, j, p = raw_field(model, xyz, jacobian=True)
    eg, jg, pg = raw_field(model, model.grid(grid_n), jacobian=True)
    assert j is not None and jg is not None
    c = pg.mean(axis=0)
    dg = rigid_design(pg, c).reshape(-1, 6)
    fit = np.linalg.pinv(dg)  # (6, 3G): the least-squares rigid motion of a grid field
    dp = rigid_design(p, c)
    rig = fit @ eg.reshape(-1)
    rig_j = fit @ jg.reshape(-1, model.size)
    e_c = e - dp @ rig
    j_c = j - np.einsum("nak,kp->nap", dp, rig_j)
    var = np.einsum("nap,pq,naq->na", j_c, model.cov, j_c)
    return Prediction(e_c * 1e3, np.sqrt(np.clip(var, 0.0, None)) * 1e3, e * 1e3, j_c)


def remove_best_rigid(diff_mm: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """``diff_mm`` (N, 3) minus its least-squares rigid motion over ``points_mm``."""
    d = rigid_design(points_mm, points_mm.mean(axis=0))
    fit = np.linalg.lstsq(d.reshape(-1, 6), diff_mm.reshape(-1), rcond=None)[0]
    return diff_mm - d @ fit


def compare_maps(a: MapModel, b: MapModel, grid_n: int = GRID_N) -> dict[str, float]:
    """Max and RMS (µm) of the difference of two maps over the common covered box after the
    best rigid motion of the difference is removed (METHOD.md §7)."""
    box = {k: (max(a.box_mm[k][0], b.box_mm[k][0]), min(a.box_mm[k][1], b.box_mm[k][1]))
           for k in "XYZ"}
    if any(hi <= lo for lo, hi in box.values()):
        raise ValueError("the two maps' covered boxes do not overlap")
    pts = MapModel(a.machine, a.links, a.basis, a.values, a.cov, box).grid(grid_n)
    ea, _, pw = raw_field(a, pts)
    eb, _, _ = raw_field(b, pts)
    d = remove_best_rigid(ea - eb, pw) * 1e3
    n = np.linalg.norm(d, axis=1)
    return {"max_um": float(n.max()), "rms_um": float(np.sqrt(np.mean(n**2))),
            "points": float(len(pts))}
