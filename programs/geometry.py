"""Pose geometry of the probing program: the exact affine map controller X Y Z → stylus tip in
the last workpiece frame at a rotary pose, the retract axis along the spindle, and the highest
points of the keep-outs (balls, rods, table rim, boxes) over a rotary sweep as retract-axis
values (transit heights at one pose: ``programs.heights``)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from contracts.setup_files import MachineFile
from identification.kinematics import ChainState, Machine, frames, solve_centre, to_model
from identification.model import Artefact

SWEEP_STEP_DEG = 2.0  # rotary sampling used to size the retract before an index
MAX_SWEEP_SAMPLES = 1_000_000  # rotary samples of one index move (175-pose grid: < 2 000)


class ProgramError(ValueError):
    """The plan cannot be turned into a program (one line naming pose/ball and reason)."""


def tip_affine(machine: Machine, state: ChainState, rot: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Stylus tip in the last workpiece frame as ``p = b + q_lin @ a`` for rotary states
    ``rot`` (N, 2; first, second rotary letter): exact, the chain is affine in the linear axes
    for fixed rotary joints (no motion errors). Returns a (N, 3, 3) and b (N, 3)."""
    r1, r2 = machine.rotary_axes
    n = len(rot)
    q = np.zeros((n, 4, 5))
    q[:, :, 3:] = rot[:, None, :]
    for k in range(3):
        q[:, k + 1, k] = 1.0
    q = q.reshape(-1, 5)
    qm = to_model(machine, {"X": q[:, 0], "Y": q[:, 1], "Z": q[:, 2], r1: q[:, 3],
                            r2: q[:, 4]}, state.linear_scale)
    f_w, f_t = frames(machine, qm, state)
    tip = np.asarray(machine.tool_tip_mm, float) + state.tip_offset_mm
    tip_f = np.einsum("nij,j->ni", f_t[:, :3, :3], tip) + f_t[:, :3, 3]
    p = np.einsum("nji,nj->ni", f_w[:, :3, :3], tip_f - f_w[:, :3, 3]).reshape(n, 4, 3)
    return p[:, 1:] - p[:, :1], p[:, 0]


@dataclass
class PoseFrame:
    """Affine map controller X Y Z → relative position at one rotary pose."""

    rot: dict[str, float]
    jac: np.ndarray  # d r / d q (3, 3): columns X, Y, Z
    jinv: np.ndarray
    spindle: np.ndarray  # spindle direction (tip → spindle), foundation frame
    r_fw: np.ndarray  # rotation foundation ← last workpiece frame
    affine: tuple[np.ndarray, np.ndarray] | None = None  # (a⁻¹, b) of tip_affine

    def solve(self, machine: Machine, points_w: np.ndarray, state: ChainState) -> np.ndarray:
        """Controller X Y Z putting the tip centre on each workpiece point (N, 3)."""
        if self.affine is None:
            r = np.array([[self.rot[a] for a in machine.rotary_axes]], float)
            a, b = tip_affine(machine, state, r)
            self.affine = (np.linalg.inv(a[0]), b[0])
        a_inv, b = self.affine
        return (points_w - b) @ a_inv


def pose_frame(machine: Machine, rot: Mapping[str, float], state: ChainState) -> PoseFrame:
    """Jacobian of the relative position w.r.t. controller linear axes (exact: affine, 1 mm)."""
    probe = np.zeros((1, 3))
    q0 = solve_centre(machine, {k: np.array([v]) for k, v in rot.items()}, probe, state)
    jac = np.empty((3, 3))
    qm_rot = to_model(machine, {k: np.array([v]) for k, v in rot.items()})
    for k in range(3):
        dq = q0.copy()
        dq[0, k] += 1.0
        qm = to_model(machine, {a: dq[:, i] for i, a in enumerate("XYZ")}, state.linear_scale)
        f_w, f_t = frames(machine, {**qm, **qm_rot}, state)
        tip = np.asarray(machine.tool_tip_mm, float) + state.tip_offset_mm
        tip_f = f_t[0, :3, :3] @ tip + f_t[0, :3, 3]
        jac[:, k] = tip_f - f_w[0, :3, 3]  # relative to the workpiece origin, q0 puts it at 0
    qm = to_model(machine, {a: q0[:, i] for i, a in enumerate("XYZ")}, state.linear_scale)
    f_w, f_t = frames(machine, {**qm, **qm_rot}, state)
    spindle = f_t[0, :3, :3] @ np.asarray(machine.spindle_axis, float)
    return PoseFrame(dict(rot), jac, np.linalg.inv(jac), spindle / np.linalg.norm(spindle),
                     f_w[0, :3, :3])


def retract_axis(pf: PoseFrame) -> tuple[int, float]:
    """The controller axis moving the tip along the spindle and its rate (mm height per mm)."""
    v = pf.jinv @ pf.spindle
    k = int(np.argmax(np.abs(v)))
    others = np.delete(v, k)
    if np.max(np.abs(others)) > 1e-9 * abs(v[k]):
        raise ProgramError(
            f"spindle axis {np.round(pf.spindle, 6).tolist()} at pose {pf.rot} is not along one "
            "linear controller axis: retract planes are not supported for this machine")
    return k, 1.0 / float(v[k])


def sweep_grid(x0: float, x1: float) -> np.ndarray:
    """Samples from x0 to x1 (both included) at most SWEEP_STEP_DEG apart."""
    span = abs(x1 - x0) / SWEEP_STEP_DEG
    if not span < MAX_SWEEP_SAMPLES:  # counted before allocating (also inf / nan)
        raise ProgramError(f"rotary index {x0:g} → {x1:g} deg: more than {MAX_SWEEP_SAMPLES} "
                           "samples; add an intermediate pose")
    n = max(2, math.ceil(span) + 1)
    return np.linspace(x0, x1, n)


def sweep_required(machine: Machine, machine_file: MachineFile, artefact: Artefact,
                   balls_w: np.ndarray, state: ChainState, k: int, b_deg: np.ndarray,
                   c_deg: np.ndarray, margin_mm: float) -> np.ndarray:
    """Retract-axis value (one per rotary sample) at which the tip is ``margin_mm`` above every
    keep-out top (balls, rod bottoms, table rim + clearance, boxes), batched over samples."""
    r1, r2 = machine.rotary_axes
    n = b_deg.shape[0]
    qm = to_model(machine, {"X": np.zeros(n), "Y": np.zeros(n), "Z": np.zeros(n),
                            r1: b_deg, r2: c_deg})
    f_w, f_t = frames(machine, qm, state)
    spindle = np.einsum("nij,j->ni", f_t[:, :3, :3], np.asarray(machine.spindle_axis, float))
    u_w = np.einsum("nji,nj->ni", f_w[:, :3, :3], spindle)
    pts, up = [], []
    for b, c in zip(artefact.balls, balls_w, strict=True):
        pts += [np.broadcast_to(c, (n, 3)),
                np.broadcast_to(c - np.array([0.0, 0.0, b.rod_length_mm]), (n, 3))]
        up += [b.diameter_mm / 2, b.rod_diameter_mm / 2]
    t = machine_file.table
    v = u_w.copy()
    v[:, 2] = 0.0
    nv = np.linalg.norm(v, axis=1, keepdims=True)
    rim = np.where(nv > 1e-12, t.radius_mm * v / np.maximum(nv, 1e-300), 0.0)
    rim[:, 2] = t.surface_z_mm
    pts.append(rim)
    up.append(t.clearance_mm)
    for box in machine_file.keep_out:
        lo, hi = np.array(box.min_mm), np.array(box.max_mm)
        for corner in np.array(np.meshgrid(*zip(lo, hi, strict=True))).T.reshape(-1, 3):
            pts.append(np.broadcast_to(corner, (n, 3)))
            up.append(t.clearance_mm)
    p = np.stack(pts, axis=1)  # (n, P, 3)
    a, b = tip_affine(machine, state, np.column_stack([b_deg, c_deg]))
    a_inv = np.linalg.inv(a)
    q = np.einsum("npi,nij->npj", p - b[:, None, :], a_inv)
    # rate: height gained per unit of the retract axis (the spindle maps onto axis k)
    rate = 1.0 / np.einsum("ni,ni->n", u_w, a_inv[:, :, k])[:, None]
    z = q[..., k] + (np.asarray(up)[None, :] + margin_mm) / rate
    return z.max(axis=1) if np.all(rate > 0) else z.min(axis=1)


