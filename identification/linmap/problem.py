"""The joint measurement model of a map: several placements of an artefact, each with its own
ball setup, sharing the links, the map of the linear axes and the probe setup (one stylus).

Parameter vector: [links | map coefficients | probe dx dy dz | balls of placement 1 | …];
internal units mm / rad. Each placement is predicted by ``model.predict`` on the exact chain
with the map's motion errors; the map's columns are ``columns.map_columns`` taken through the
same implicit-function step, dq/dc = −(dg/dq)⁻¹ dg/dc.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from identification.kinematics import ChainState, Machine, rotary_columns, tip_minus_ball, to_model
from identification.linmap.columns import map_columns
from identification.linmap.terms import MapBasis
from identification.model import Artefact, Centres, Layout, chain_links, predict


class MapError(ValueError):
    """The placements cannot give a map (too few poses, an unknown name …): the message says
    why, for the operator."""


@dataclass(frozen=True)
class Placement:
    """One probing run: the artefact where it stood and the centres measured on it; with the
    touches behind each centre (``points_mm`` (K, n, 3), ``radius_mm`` (K,) ball + stylus)
    the map re-fits each sphere in the frame its own estimate corrects (``refit``)."""

    name: str
    artefact: Artefact
    centres: Centres
    points_mm: np.ndarray | None = None
    radius_mm: np.ndarray | None = None
    fixed_radius: bool = False

    def with_xyz(self, xyz_mm: np.ndarray) -> Placement:
        """The same placement with other centre positions (the touches kept)."""
        return replace(self, centres=replace(self.centres, xyz_mm=np.asarray(xyz_mm, float)))


@dataclass(frozen=True)
class JointLayout:
    links: tuple[str, ...]
    basis: MapBasis
    n_balls: tuple[int, ...]

    @property
    def map_slice(self) -> slice:
        return slice(len(self.links), len(self.links) + self.basis.size)

    @property
    def tip_slice(self) -> slice:
        k = self.map_slice.stop
        return slice(k, k + 3)

    def ball_slice(self, i: int) -> slice:
        k = self.tip_slice.stop + 3 * sum(self.n_balls[:i])
        return slice(k, k + 3 * self.n_balls[i])

    @property
    def size(self) -> int:
        return self.tip_slice.stop + 3 * sum(self.n_balls)

    @property
    def n_model(self) -> int:
        """Links and map: the parameters of the machine (a prediction needs only these)."""
        return self.map_slice.stop

    def names(self, placements: Sequence[Placement]) -> list[str]:
        out = list(self.links) + self.basis.names + [f"probe d{a}" for a in "xyz"]
        for pl in placements:
            out += [f"{pl.name} ball {b} d{a}" for b in pl.artefact.ids for a in "xyz"]
        return out

    def local(self, i: int) -> tuple[Layout, np.ndarray]:
        """The placement's ``model.Layout`` and the global index of each of its parameters."""
        lay = Layout(self.links, self.n_balls[i])
        idx = np.concatenate([np.arange(len(self.links)),
                              np.arange(self.ball_slice(i).start, self.ball_slice(i).stop),
                              np.arange(self.tip_slice.start, self.tip_slice.stop)])
        return lay, idx


@dataclass
class Evaluation:
    """Predicted centres per placement (controller mm) and, when asked, d(pred)/dp (K, 3, P);
    predicted calibrated distances with their Jacobian and stds (mm)."""

    pred: list[np.ndarray]
    jac: list[np.ndarray] | None
    dist: np.ndarray
    dist_jac: np.ndarray
    dist_cal: np.ndarray
    dist_std: np.ndarray


def _g(machine: Machine, rot_model: dict, balls_w: np.ndarray, q: np.ndarray,
       state: ChainState) -> np.ndarray:
    qm = to_model(machine, {k: q[:, i] for i, k in enumerate("XYZ")}, state.linear_scale)
    return tip_minus_ball(machine, {**qm, **rot_model}, balls_w, state)


def evaluate(machine: Machine, placements: Sequence[Placement], layout: JointLayout,
             p: np.ndarray, jacobian: bool = False) -> Evaluation:
    """The model at ``p`` for every placement (and the calibrated distances of each artefact)."""
    p = np.asarray(p, float)
    coef = p[layout.map_slice]
    motion = layout.basis.motion_errors(coef)
    preds, jacs = [], []
    dist, dcal, dstd, djac = [], [], [], []
    for i, pl in enumerate(placements):
        lay, idx = layout.local(i)
        pred, dq = predict(machine, pl.artefact, lay, p[idx], pl.centres, jacobian=jacobian,
                           motion_errors=motion)
        preds.append(pred)
        if jacobian:
            assert dq is not None
            j = np.zeros((len(pl.centres), 3, layout.size))
            j[:, :, idx] = dq
            if layout.basis.size:
                j[:, :, layout.map_slice] = _map_dq(machine, pl, lay, p[idx], pred, motion,
                                                    layout.basis)
            jacs.append(j)
        w = pl.artefact.nominal_mm + p[layout.ball_slice(i)].reshape(-1, 3)
        ids = pl.artefact.ids
        for cd in pl.artefact.distances:
            a, b = ids.index(cd.ball_a), ids.index(cd.ball_b)
            v = w[a] - w[b]
            d = float(np.linalg.norm(v))
            row = np.zeros(layout.size)
            s = layout.ball_slice(i).start
            row[s + 3 * a: s + 3 * a + 3] = v / d
            row[s + 3 * b: s + 3 * b + 3] = -v / d
            dist.append(d)
            djac.append(row)
            dcal.append(cd.distance_mm)
            dstd.append(cd.std_um * 1e-3)
    return Evaluation(preds, jacs if jacobian else None, np.array(dist),
                      np.array(djac).reshape(-1, layout.size), np.array(dcal), np.array(dstd))


def centre_jq(machine: Machine, pl: Placement, lay: Layout, p_local: np.ndarray,
              q: np.ndarray, motion: dict) -> tuple[np.ndarray, ChainState, np.ndarray, dict]:
    """dg/dq (K, 3, 3) at controller positions ``q`` of one placement's centres (g = tip −
    ball, foundation frame), with the chain state, balls and rotary joints it was taken at."""
    links, dballs, dtip, _ = lay.unpack(p_local)
    state = ChainState(links=chain_links(machine, links), tip_offset_mm=dtip,
                       motion_errors=motion)
    c = pl.centres
    balls_w = pl.artefact.nominal_mm[c.ball] + dballs[c.ball]
    rot_model = to_model(machine, rotary_columns(machine, c.b_deg, c.c_deg))
    g0 = _g(machine, rot_model, balls_w, q, state)
    jq = np.empty((len(c), 3, 3))
    for k in range(3):  # dg/dq by unit steps (affine to µm/mm curvature: as model.predict)
        dq = q.copy()
        dq[:, k] += 1.0
        jq[:, :, k] = _g(machine, rot_model, balls_w, dq, state) - g0
    return jq, state, balls_w, rot_model


def _map_dq(machine: Machine, pl: Placement, lay: Layout, p_local: np.ndarray, q: np.ndarray,
            motion: dict, basis: MapBasis) -> np.ndarray:
    """dq/dc (K, 3, M) at the solution ``q`` of one placement."""
    jq, state, balls_w, rot_model = centre_jq(machine, pl, lay, p_local, q, motion)
    qm = {**to_model(machine, {k: q[:, i] for i, k in enumerate("XYZ")}), **rot_model}
    dg = map_columns(machine, qm, state, balls_w, basis)
    return -np.linalg.solve(jq, dg)


def covered_ranges(machine: Machine, placements: Sequence[Placement]
                   ) -> dict[str, tuple[float, float]]:
    """Per linear axis the [min, max] of its model joint value (mm) at the measured centres of
    every placement: the range the map is defined over."""
    out = {}
    for i, a in enumerate("XYZ"):
        q = np.concatenate([to_model(machine, {a: pl.centres.xyz_mm[:, i]})[a]
                            for pl in placements])
        out[a] = (float(q.min()), float(q.max()))
    return out
