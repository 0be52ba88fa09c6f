"""Analytic Jacobian columns of the map's coefficients, mirroring ``model._link_columns``.

A motion error of axis k enters its branch as A_k = L_k · M_k(q) · E_k(q) (kinematics.axis_htm:
location, motion, then the small error HTM E = Trans(t) · Rot_x · Rot_y · Rot_z of the six
components, seed 003 §2). For the coefficient c of degree d of component s,

    dg/dc = ± P_k · L_k M_k · dE_k/de_s · S_{k+1} · point · P_d(u(q_k)),

P_k the axes before k, S_{k+1} those after it applied to the point (the ball on the workpiece
branch, minus; the stylus tip on the tool branch, plus), exact at the current errors.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from identification.kinematics import (
    ChainState,
    Machine,
    axis_frame,
    axis_htm,
)
from identification.linmap.terms import MapBasis

_GEN = np.zeros((3, 4, 4))  # generators of the rotations about x, y, z (4×4 skew parts)
_GEN[0, 2, 1], _GEN[0, 1, 2] = 1.0, -1.0
_GEN[1, 0, 2], _GEN[1, 2, 0] = 1.0, -1.0
_GEN[2, 1, 0], _GEN[2, 0, 1] = 1.0, -1.0


def _rot(index: int, angle: np.ndarray) -> np.ndarray:
    n = angle.shape[0]
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros((n, 4, 4))
    m[:, 3, 3] = 1.0
    i, j = [(1, 2), (2, 0), (0, 1)][index]
    m[:, index, index] = 1.0
    m[:, i, i] = c
    m[:, j, j] = c
    m[:, i, j] = -s
    m[:, j, i] = s
    return m


def small_htm_derivatives(e: np.ndarray) -> np.ndarray:
    """(6, N, 4, 4) exact d/de_s of Trans(t) · Rot_x(a) · Rot_y(b) · Rot_z(c) at errors e (N, 6)."""
    n = e.shape[0]
    out = np.zeros((6, n, 4, 4))
    for s in range(3):
        out[s, :, s, 3] = 1.0  # d(T·R)/dt_s = E_s3 · R = E_s3
    t = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    t[:, :3, 3] = e[:, :3]
    r = [_rot(k, e[:, 3 + k]) for k in range(3)]
    for k in range(3):
        f = list(r)
        f[k] = f[k] @ _GEN[k]  # d Rot_k / d angle = Rot_k · K_k
        out[3 + k] = t @ f[0] @ f[1] @ f[2]
    return out


def map_columns(machine: Machine, q_model: Mapping[str, np.ndarray], state: ChainState,
                points_w: np.ndarray, basis: MapBasis) -> np.ndarray:
    """dg/dc (K, 3, M) with g = F_T_T · tip − F_T_W · points_w (points in the last workpiece
    frame, mm), for every coefficient of ``basis`` at the chain state ``state`` (whose
    ``motion_errors`` are the map's current functions)."""
    k_obs = points_w.shape[0]
    out = np.zeros((k_obs, 3, basis.size))
    if not basis.size:
        return out
    tip = np.broadcast_to(np.asarray(machine.tool_tip_mm, float) + state.tip_offset_mm,
                          (k_obs, 3))
    for chain, point, sign in ((machine.workpiece_chain, points_w, -1.0),
                               (machine.tool_chain, tip, 1.0)):
        wanted = [a for a in chain if basis.axis_terms(a)]
        if not wanted:
            continue
        full = [axis_htm(machine.axes[a], np.asarray(q_model[a], float), state.links,
                         state.motion_errors.get(a)) for a in chain]
        v = np.concatenate([point, np.ones((k_obs, 1))], axis=1)[..., None]
        suffix = [v] * (len(chain) + 1)
        for k in range(len(chain) - 1, -1, -1):
            suffix[k] = full[k] @ suffix[k + 1]
        prefix = np.broadcast_to(np.eye(4), (k_obs, 4, 4))
        for k, a in enumerate(chain):
            if a in wanted:
                ax = machine.axes[a]
                q = np.asarray(q_model[a], float)
                bare = axis_htm(ax, q, state.links, None)  # location · motion, no motion error
                fn = state.motion_errors.get(a)
                e = np.zeros((k_obs, 6)) if fn is None else np.asarray(fn(q), float).reshape(
                    k_obs, 6)
                de = small_htm_derivatives(e)
                r0 = axis_frame(ax)
                if r0 is not None:  # an inclined axis' errors act in its frame (kinematics)
                    h = np.eye(4)
                    h[:3, :3] = r0
                    de = h @ de @ h.T
                idx = basis.axis_terms(a)
                phi = basis.values(a, q)  # (K, n)
                left = prefix @ bare
                per_slot = {}
                for j, i in enumerate(idx):
                    s = basis.terms[i].slot
                    if s not in per_slot:
                        per_slot[s] = sign * (left @ (de[s] @ suffix[k + 1]))[:, :3, 0]
                    out[:, :, i] = per_slot[s] * phi[:, j, None]
            prefix = prefix @ full[k]
    return out
