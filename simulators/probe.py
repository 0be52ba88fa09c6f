"""Probe physics: where the stylus sphere, moving along a commanded line, meets a ball sphere.

The probing move is a straight line in controller X, Y, Z with the rotary axes fixed. Contact is
where ``|tip(q(s)) - ball(q(s))| = R_ball + r_stylus`` through the TRUE chain (METHOD.md §2,
thesis Eq. 3.1). Without position-dependent motion errors the tip-ball vector is affine in the
linear joints, so the distance squared is a quadratic in s and the root is closed-form (exact);
with motion errors the distance is sampled to bracket the first crossing and ``brentq`` refines
it on the exact chain. The latch follows the contact by the pre-travel, then offsets and noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from simulators.truth import TruthModel

_SAMPLES = 65  # bracketing samples along a probing move when motion errors are present
_S_TOL = 1e-13  # root tolerance in move fraction: < 1e-9 mm on any realistic move
_COLLISION_TOL_MM = 5e-3  # a positioning move may graze within motion-error size, not deeper


@dataclass(frozen=True)
class Contact:
    """First contact of a probing move (``s`` is the fraction of the move, 0..1)."""

    s: float
    target: int  # ball index, or -1 - k for obstacle k
    contact_ctrl: np.ndarray  # controller X Y Z at contact


def _targets(truth: TruthModel, t_s: float, b_deg: float, c_deg: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (T, 3) in the last workpiece frame, contact radii (T,), ids (T,)."""
    centres = truth.ball_centres_mm(t_s, b_deg, c_deg)
    present = np.array([i for i in range(len(centres)) if i not in truth.absent], int)
    c = [centres[present]]
    rad = [truth.ball_radii_mm[present] + truth.stylus_radius_mm]
    ids = [present]
    if len(truth.obstacle_radii_mm):
        c.append(truth.obstacle_centres_mm)
        rad.append(truth.obstacle_radii_mm + truth.stylus_radius_mm)
        ids.append(-1 - np.arange(len(truth.obstacle_radii_mm)))
    return np.vstack(c), np.concatenate(rad), np.concatenate(ids)


def _gap(truth: TruthModel, q: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Tip-minus-target vectors (S, T, 3) in the foundation frame for joints q (S, 5)."""
    tip, rot, org = truth.chain(q)
    wc = np.einsum("sij,tj->sti", rot, centres) + org[:, None, :]
    return tip[:, None, :] - wc


def first_contact(truth: TruthModel, start_ctrl: np.ndarray, end_ctrl: np.ndarray,
                  b_deg: float, c_deg: float, t_s: float) -> Contact | None:
    """First contact of the stylus with a ball or obstacle on the line start → end, or None.

    A move that starts already in contact returns ``s = 0`` (the probe is deflected)."""
    p0 = np.asarray(start_ctrl, float)
    p1 = np.asarray(end_ctrl, float)
    centres, rho, ids = _targets(truth, t_s, b_deg, c_deg)
    if len(rho) == 0:
        return None

    def joints(s: np.ndarray) -> np.ndarray:
        s = np.atleast_1d(s)
        q = np.empty((len(s), 5))
        q[:, :3] = p0 + s[:, None] * (p1 - p0)
        q[:, 3], q[:, 4] = b_deg, c_deg
        return q

    g = _gap(truth, joints(np.array([0.0, 1.0])), centres)  # exact at both ends
    g0, d = g[0], g[1] - g[0]
    a = np.einsum("ti,ti->t", d, d)
    b = 2 * np.einsum("ti,ti->t", g0, d)
    c = np.einsum("ti,ti->t", g0, g0) - rho**2
    s_hit = np.full(len(rho), np.inf)
    s_hit[c <= 0] = 0.0
    disc = b * b - 4 * a * c
    ok = (c > 0) & (disc >= 0) & (a > 0)
    sq = np.sqrt(np.where(ok, disc, 0.0))
    # Smaller root, written to avoid cancellation: 2c / (-b + sqrt(disc)).
    den = -b + sq
    root = np.where(ok & (den > 0), 2 * c / np.where(den > 0, den, 1.0), np.inf)
    s_hit = np.where(ok, root, s_hit)
    k = int(np.argmin(s_hit))
    if not truth.has_motion_errors:
        # The tip-ball vector is affine in the linear joints: the quadratic root is exact.
        if not s_hit[k] <= 1.0:
            return None
        s = float(s_hit[k])
    else:
        found = _refine(truth, joints, centres, rho, s_hit, k)
        if found is None:
            return None
        s, k = found
    return Contact(s=s, target=int(ids[k]), contact_ctrl=p0 + s * (p1 - p0))


def _refine(truth: TruthModel, joints, centres: np.ndarray, rho: np.ndarray,
            s_hit: np.ndarray, k: int) -> tuple[float, int] | None:
    """Exact first root with position-dependent motion errors: secant steps from the affine
    guess (the nonlinearity is µm over the move, two or three evaluations), with a sampled
    bracket and ``brentq`` as the fallback."""

    def f(s: float, kk: int = k) -> float:
        return float(np.linalg.norm(_gap(truth, joints(np.array([s])), centres[kk:kk + 1])[0, 0])
                     - rho[kk])

    if np.isfinite(s_hit[k]) and s_hit[k] > 0:
        s_a = float(s_hit[k])
        f_a = f(s_a)
        s_b = s_a - 1e-6 if s_a > 1e-6 else s_a + 1e-6
        f_b = f(s_b)
        for _ in range(12):
            if f_a == f_b:
                break
            s_n = s_a - f_a * (s_a - s_b) / (f_a - f_b)
            s_b, f_b = s_a, f_a
            s_a, f_a = s_n, f(s_n)
            if abs(s_a - s_b) < _S_TOL:
                break
        ok = abs(s_a - s_b) < 1e-9 and 0.0 <= s_a <= 1.0
        # Guard against having converged onto the far root: the distance must be decreasing.
        if ok and f(max(s_a - 1e-7, 0.0)) > 0:
            return s_a, k
    grid = np.linspace(0.0, 1.0, _SAMPLES)
    fk = np.linalg.norm(_gap(truth, joints(grid), centres), axis=2) - rho  # (S, T)
    if np.any(fk[0] <= 0):
        return 0.0, int(np.argmin(fk[0]))
    inside = fk <= 0
    if not inside.any():
        return None
    first = np.where(inside.any(axis=0), inside.argmax(axis=0), _SAMPLES)
    kk = int(np.argmin(first))
    j = int(first[kk])
    s = brentq(lambda x: f(x, kk), grid[j - 1], grid[j], xtol=_S_TOL,
               rtol=4 * np.finfo(float).eps)
    return float(s), kk


def collision(truth: TruthModel, q_start: np.ndarray, q_end: np.ndarray, t_s: float,
              step_mm: float = 0.5, step_deg: float = 0.25) -> str | None:
    """What the stylus would hit on a positioning move (linear and rotary joints interpolated),
    or None. Checks balls, rods and the table; sampled (a safety check, not a metrology one)."""
    q0 = np.asarray(q_start, float)
    q1 = np.asarray(q_end, float)
    if np.array_equal(q0[3:], q1[3:]):
        # Fixed rotary axes: the tip moves on a straight line in the workpiece frame (to within
        # the motion errors): cached affine map, no chain evaluation.
        n = min(max(int(np.ceil(np.linalg.norm(q1[:3] - q0[:3]) / step_mm)) + 1, 2), 4000)
        amat, off = truth.affine_map(float(q0[3]), float(q0[4]))
        s = np.linspace(0.0, 1.0, n)
        tip_w = (q0[:3] + s[:, None] * (q1[:3] - q0[:3])) @ amat.T + off
    else:
        n = int(np.ceil(np.linalg.norm(q1[:3] - q0[:3]) / step_mm
                        + np.max(np.abs(q1[3:] - q0[3:])) / step_deg)) + 1
        n = min(max(n, 2), 4000)
        s = np.linspace(0.0, 1.0, n)
        q = q0 + s[:, None] * (q1 - q0)
        tip, rot, org = truth.chain(q)
        tip_w = np.einsum("sji,sj->si", rot, tip - org)  # tip in the last workpiece frame
    r = truth.stylus_radius_mm
    # Ball positions: creep/sag change slowly, evaluate once for the move.
    centres = truth.ball_centres_mm(t_s, float(q0[3]), float(q0[4]))
    for i, ball in enumerate(truth.artefact.balls):
        if i in truth.absent:
            continue
        d = np.linalg.norm(tip_w - centres[i], axis=1)
        # A move may start in contact (the retract after a touch, pre-travel past the surface):
        # only going deeper than where it started, or entering, is a collision.
        if np.any(d[1:] < min(ball.diameter_mm / 2 + r, d[0]) - _COLLISION_TOL_MM):
            return f"stylus hits ball {ball.id}"
        # Rod: a cylinder from the table surface up to the ball centre (last workpiece frame z).
        base_z = truth.machine_file.table.surface_z_mm
        rel = tip_w - centres[i]
        below = (tip_w[:, 2] > base_z) & (rel[:, 2] < 0)
        if np.any(below & (np.hypot(rel[:, 0], rel[:, 1]) < ball.rod_diameter_mm / 2 + r)):
            return f"stylus hits the rod of ball {ball.id}"
    table = truth.machine_file.table
    on_table = np.hypot(tip_w[:, 0], tip_w[:, 1]) < table.radius_mm + r
    if np.any(on_table & (tip_w[:, 2] < table.surface_z_mm + r)):
        return "stylus hits the table"
    return None
