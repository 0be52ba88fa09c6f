"""Estimation from centres given in an instrument's frame, or with an uncertainty per centre.

An instrument (CMM, camera, tracker) reports a centre in its own axes: m = R·q + t, with q the
controller X Y Z the model predicts (``model.predict``, METHOD.md §3) and (R, t) a rigid motion
nobody measured — six setup parameters, estimated with the setup and link errors (Gauss-Newton
on the exact chain, the rotation updated multiplicatively: R ← Exp(ω)·R about the instrument
axes). Which of them the data can separate is derived as for the links
(``identifiability.py``): the Jacobian with setup columns first, then the six frame columns,
then the link candidates, each kept when it raises the numerical rank. A frame direction that
does not (e.g. the translation on a machine whose tool branch has no rotary axis: it is the
probe offset) stays at the rigid best fit of the nominal prediction and is named; a link whose
effect the frame absorbs (a rotation of all readings) is dropped and named with what absorbs it.

Weights: a centre std per axis (given), per centre (``u_um`` of the centres file), or a
posteriori from the residuals as in ``estimate.estimate`` (per axis, then a variance factor).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from identification.estimate import (
    ANGLE_LENGTH_MM,
    DEFAULT_SIGMA_UM,
    MAX_ITER,
    STEP_TOL_MM,
    Estimate,
    RankDeficientError,
    a_posteriori,
    check_links,
    distance_rows,
    fit_status,
    unobservable,
)
from identification.identifiability import RANK_TOL, explain_absorption, numerical_rank
from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict

FRAME_NAMES = ("frame tx", "frame ty", "frame tz", "frame rx", "frame ry", "frame rz")


@dataclass
class FrameFit:
    """Instrument ← machine rigid motion: m = rotation · q + translation_mm."""

    rotation: np.ndarray  # (3, 3)
    translation_mm: np.ndarray  # (3,)
    std: np.ndarray  # (6,) translation µm, small rotation µrad about the instrument axes;
    # NaN for a direction the data cannot separate from the setup (held at the rigid fit)
    free: tuple[bool, ...]  # per FRAME_NAMES: estimated (True) or held (False)
    absorbed_by: dict[str, str]  # held frame directions → the setup columns they equal

    def to_machine(self, xyz_mm: np.ndarray) -> np.ndarray:
        """Instrument coordinates → controller X Y Z (R^T (m − t), row-wise)."""
        return (np.asarray(xyz_mm, float) - self.translation_mm) @ self.rotation

    def rotation_vector_deg(self) -> np.ndarray:
        return rotation_vector_deg(self.rotation)


def rotation_vector_deg(r: np.ndarray) -> np.ndarray:
    """A rotation matrix as axis × angle (°)."""
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0)))
    if angle < 1e-12:
        return np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if np.linalg.norm(axis) < 1e-9 * angle:  # 180°: the axis from the symmetric part
        w, v = np.linalg.eigh((r + r.T) / 2.0)
        axis = v[:, np.argmax(w)]
    return np.degrees(angle) * axis / np.linalg.norm(axis)


def kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with R·a + t ≈ b in least squares (proper rotation); a, b (K, 3)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, s, vt = np.linalg.svd((a - ca).T @ (b - cb))
    if s.size < 3 or s[1] < 1e-9 * max(s[0], 1e-300):
        raise RankDeficientError("instrument frame: the centres are collinear (or one point): "
                                 "they do not fix a rotation; need three non-collinear centres")
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


def _skew_cols(v: np.ndarray) -> np.ndarray:
    """(K, 3, 3): d(Exp(ω)·v)/dω at ω = 0, i.e. −[v]×."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = v[:, 2], -v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = -v[:, 2], v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = v[:, 1], -v[:, 0]
    return out


def _exp(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-15:
        return np.eye(3) + k
    return np.eye(3) + math.sin(th) / th * k + (1 - math.cos(th)) / th**2 * (k @ k)


def _frame_cols(rq: np.ndarray) -> np.ndarray:
    """(K, 3, 6) d m / d(t, ω)."""
    cols = np.zeros((rq.shape[0], 3, 6))
    cols[:, :, :3] = np.eye(3)
    cols[:, :, 3:] = _skew_cols(rq)
    return cols


def select(machine: Machine, artefact: Artefact, centres: Centres, rotation: np.ndarray | None
           ) -> tuple[tuple[str, ...], dict[str, str], list[bool], dict[str, str]]:
    """(identifiable links, dropped links → what absorbs them, frame columns kept, held frame
    directions → what absorbs them); ``rotation`` None: no frame (machine axes)."""
    cands = machine.location_error_names()
    full = Layout(tuple(cands), len(artefact.balls), scale=False)
    q, jac = predict(machine, artefact, full, np.zeros(full.size), centres, jacobian=True)
    cols = [jac]
    names = full.names(artefact.ids)
    if rotation is not None:
        cols = [np.einsum("ij,kjp->kip", rotation, jac), _frame_cols(q @ rotation.T)]
        names = names + list(FRAME_NAMES)
    j = np.concatenate(cols, axis=2).reshape(-1, len(names))
    kept = list(range(len(cands), full.size))
    if numerical_rank(j[:, kept]) < len(kept):
        raise RankDeficientError("setup errors alone are not identifiable from these poses "
                                 "(too few poses or balls; need at least two distinct "
                                 "indexations)")
    frame_free, held = [], {}
    for i in range(full.size, len(names)):
        if numerical_rank(j[:, [*kept, i]]) > len(kept):
            kept.append(i)
            frame_free.append(True)
        else:
            frame_free.append(False)
            held[names[i]] = explain_absorption(j[:, i], j[:, kept], [names[k] for k in kept])
    dropped = {}
    for i, name in enumerate(cands):
        if numerical_rank(j[:, [*kept, i]]) > len(kept):
            kept.append(i)
        else:
            dropped[name] = explain_absorption(j[:, i], j[:, kept], [names[k] for k in kept])
    return tuple(c for i, c in enumerate(cands) if i in kept), dropped, frame_free, held


def estimate_weighted(machine: Machine, artefact: Artefact, centres: Centres,
                      links: Sequence[str] | None = None, *, frame: bool = False,
                      sigma_um: np.ndarray | Sequence[float] | None = None,
                      use_distances: bool = True, max_iter: int = MAX_ITER
                      ) -> tuple[Estimate, FrameFit | None]:
    """Setup + ``links`` (None: the identifiable set) [+ the instrument frame], weighted by
    ``sigma_um``: (3,) per axis or (K,) / (K, 3) per centre, given; None: a posteriori."""
    k = len(centres)
    if k == 0:
        raise RankDeficientError("no ball centre to estimate from")
    rot0 = t0 = None
    if frame:
        q0, _ = predict(machine, artefact, Layout((), len(artefact.balls)),
                        np.zeros(3 * len(artefact.balls) + 3), centres)
        rot0, t0 = kabsch(q0, centres.xyz_mm)
    ident, dropped, free, held = select(machine, artefact, centres, rot0)
    chosen = ident if links is None else tuple(links)
    check_links(machine, chosen)
    use_dist = bool(use_distances and artefact.distances)
    layout = Layout(chosen, len(artefact.balls), scale=use_dist)
    names = layout.names(artefact.ids) + [n for n, f in zip(FRAME_NAMES, free, strict=False)
                                          if f]
    given = sigma_um is not None
    sig = np.asarray(DEFAULT_SIGMA_UM if sigma_um is None else sigma_um, float)
    sig = np.broadcast_to(sig[:, None] if sig.shape == (k,) else sig, (k, 3)).copy()
    if not np.all(np.isfinite(sig) & (sig > 0)):
        raise ValueError("centre uncertainties must be positive numbers")
    fcols = np.array([i for i, f in enumerate(free) if f], int) if frame else np.zeros(0, int)
    n_par = layout.size + fcols.size
    unit_len = np.ones(n_par)
    unit_len[[i for i, n in enumerate(layout.links) if n[1] in "ABC"]] = ANGLE_LENGTH_MM
    if layout.scale:
        unit_len[layout.size - 1] = ANGLE_LENGTH_MM
    unit_len[layout.size:][fcols >= 3] = ANGLE_LENGTH_MM

    def system(p, rot, t, s_mm):
        q, jac = predict(machine, artefact, layout, p, centres, jacobian=True)
        res = centres.xyz_mm - (q @ rot.T + t) if frame else centres.xyz_mm - q
        jm = np.einsum("ij,kjp->kip", rot, jac) if frame else jac
        if frame:
            jm = np.concatenate([jm, _frame_cols(q @ rot.T)[:, :, fcols]], axis=2)
        rw, jw = (res / s_mm).ravel(), (jm / s_mm[:, :, None]).reshape(-1, n_par)
        dres = np.zeros(0)
        if use_dist:
            d, dj, dstd = distance_rows(artefact, layout, p)
            dres = np.array([cd.distance_mm for cd in artefact.distances]) - d
            dj = np.concatenate([dj, np.zeros((len(d), fcols.size))], axis=1)
            rw, jw = np.concatenate([rw, dres / dstd]), np.vstack([jw, dj / dstd[:, None]])
        return rw, jw, res, dres

    def solve(p, rot, t, s_mm):
        converged, it = False, 0
        for _ in range(max_iter):
            it += 1
            rw, jw, res, dres = system(p, rot, t, s_mm)
            norms = np.linalg.norm(jw, axis=0)
            if np.any(norms == 0):
                zero = [names[i] for i in np.flatnonzero(norms == 0)]
                raise RankDeficientError(f"parameters {zero} have no effect on these centres")
            sv = np.linalg.svd(jw / norms, compute_uv=False)
            if jw.shape[0] < n_par or sv[-1] < RANK_TOL * sv[0]:
                raise RankDeficientError(f"rank-deficient pose set: {k} centres cannot separate "
                                         f"the {n_par} parameters (condition number "
                                         f"{sv[0] / max(sv[-1], 1e-300):.3g}); add indexations "
                                         "or estimate fewer link errors (--links)")
            step = np.linalg.lstsq(jw / norms, rw, rcond=None)[0] / norms
            p = p + step[:layout.size]
            if frame:
                fs = np.zeros(6)
                fs[fcols] = step[layout.size:]
                rot, t = _exp(fs[3:]) @ rot, t + fs[:3]
            if np.linalg.norm(step * unit_len) < STEP_TOL_MM:
                converged = True
                break
        rw, jw, res, dres = system(p, rot, t, s_mm)
        return p, rot, t, converged, it, rw, jw, res, dres

    p0 = np.zeros(layout.size)
    rot, t = (rot0, t0) if frame else (np.eye(3), np.zeros(3))
    s_mm = sig * 1e-3
    p, rot, t, converged, it, rw, jw, res, dres = solve(p0, rot, t, s_mm)
    dof_axis = k - n_par / 3.0
    sigma_dof = math.inf
    sig_report = np.sqrt(np.mean(sig**2, axis=0))
    if not given and dof_axis > 3:
        sig_axis = np.sqrt(np.sum(res**2, axis=0) / dof_axis)
        if np.all(sig_axis > 0):
            sigma_dof, s_mm = dof_axis, np.broadcast_to(sig_axis, (k, 3)).copy()
            sig_report = sig_axis * 1e3
            p, rot, t, c2, it2, rw, jw, res, dres = solve(p, rot, t, s_mm)
            converged, it = converged and c2, it + it2
    norms = np.linalg.norm(jw, axis=0)
    _, s, vt = np.linalg.svd(jw / norms, full_matrices=False)
    cond = float(s[0] / s[-1])
    cov = ((vt.T / s**2) @ vt) / np.outer(norms, norms)
    cov, sig_report, sigma_dof, warns = a_posteriori(rw, n_par, cov, sig_report, sigma_dof,
                                                     given)
    status, more = fit_status(cond, converged, max_iter)
    warns += more
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    unobs, absorbed = unobservable(layout, dropped)
    fit = None
    if frame:
        fstd = np.full(6, np.nan)
        fstd[fcols] = std[layout.size:] * np.where(fcols < 3, 1e3, 1e6)
        fit = FrameFit(rot, t, fstd, tuple(free), held)
        res = res @ rot  # report residuals in controller X Y Z
        for name, by in held.items():
            unobs.append(name)
            absorbed[name] = by + " (held at the rigid best fit of the nominal prediction)"
    est = Estimate(layout=layout, ball_ids=list(artefact.ids), p=p, std=std[:layout.size],
                   cov=cov[:layout.size, :layout.size], residual_mm=res,
                   distance_residual_um=dres * 1e3,
                   residual_rms_um=float(np.sqrt(np.mean(res**2)) * 1e3), condition_number=cond,
                   sigma_um=sig_report, sigma_given=given, iterations=it, converged=converged,
                   status=status, unobservable=unobs, absorbed_by=absorbed, warnings=warns,
                   sigma_dof=sigma_dof)
    return est, fit
