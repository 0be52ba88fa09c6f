"""Transit heights from the keep-out geometry at one pose: the lowest retract-axis value at which
a move over a horizontal rectangle keeps the stylus a margin clear of every ball, rod, the table
and every keep-out box — exact sphere profiles, not "highest top nearby + a fixed clearance".

At a fixed rotary pose the controller X Y Z map rigidly onto the workpiece frame
(``programs.geometry.PoseFrame``), the retract axis runs along the spindle, so a horizontal move
is horizontal in the workpiece too. The stylus tip (radius r) keeps ``margin`` from a sphere of
radius R centred at horizontal distance d from the move when its height above the centre is at
least ``sqrt((R + r + margin)² − d²)`` (nothing when d ≥ R + r + margin). A rod is a cylinder
from its foot to its ball's centre, covered by spheres along its axis ``ROD_STEP_MM`` apart
(radius ``sqrt(ρ² + (step/2)²)`` contains every point within ρ of the axis), so a tilted rod is
cleared along its whole length, not only at its ends. The table (a disc with its clearance) and
the boxes (their projected hull) are handled as planes and footprints. The stylus stem rises
from the tip along the spindle: above a keep-out when the tip is. ``programs.safety`` checks
the result; the property test in tests/test_plan_moves.py checks the margin by sampling.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contracts.setup_files import MachineFile
from identification.kinematics import ChainState, Machine
from identification.model import Artefact
from programs.geometry import PoseFrame

ROD_STEP_MM = 2.0


@dataclass
class PoseHeights:
    """The keep-outs of one pose in controller coordinates, ready for ``transit``."""

    k: int  # retract axis (0..2)
    rate: float  # height gained per unit of the retract axis (±1 on a rigid chain)
    hz: list[int]  # the two horizontal axes
    c_h: np.ndarray  # (S, 2) sphere centres, horizontal axes
    c_z: np.ndarray  # (S,) sphere centres, retract axis
    radius: np.ndarray  # (S,) keep-out radius + stylus radius + margin
    plane: np.ndarray  # table plane: retract value = plane[0] + plane[1:] · horizontal
    widen: float  # horizontal growth of the table keep-out (stylus radius + margin) in value
    lift: float  # table clearance + stylus radius + margin, in retract-axis units
    rim: float  # retract value clearing the table's highest point (+ lift)
    boxes: list[tuple[np.ndarray, np.ndarray, float]]  # grown footprint lo, hi; required value

    @property
    def up(self) -> float:
        return 1.0 if self.rate > 0 else -1.0

    def higher(self, *values: float) -> float:
        """The highest of retract-axis values (the sign of the axis decides)."""
        return max(values) if self.rate > 0 else min(values)

    def transit(self, a: np.ndarray, b: np.ndarray) -> float:
        """Lowest retract value for a move between horizontal points a and b: any two-axis
        rapid, even a non-linear one, stays in their rectangle, so the rectangle is cleared."""
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        d = np.linalg.norm(np.maximum(np.maximum(lo - self.c_h, self.c_h - hi), 0.0), axis=1)
        near = d < self.radius
        need = [self.table(lo, hi)]
        if near.any():
            rise = np.sqrt(self.radius[near] ** 2 - d[near] ** 2) / abs(self.rate)
            need.append(self.higher(*(self.c_z[near] + self.up * rise)))
        for blo, bhi, z in self.boxes:
            if np.all(lo <= bhi) and np.all(blo <= hi):
                need.append(z)
        return self.higher(*need)

    def table(self, lo: np.ndarray, hi: np.ndarray) -> float:
        """The table plane under the rectangle (+ lift), never above its rim."""
        corners = [self.plane[0] + self.plane[1:] @ np.array([x, y]) for x in (lo[0], hi[0])
                   for y in (lo[1], hi[1])]
        z = self.higher(*corners) + self.up * self.widen + self.lift
        return min(z, self.rim) if self.rate > 0 else max(z, self.rim)


def pose_heights(machine: Machine, machine_file: MachineFile, artefact: Artefact,
                 balls_w: np.ndarray, pf: PoseFrame, state: ChainState, k: int,
                 stylus_radius_mm: float, margin_mm: float) -> PoseHeights:
    """The keep-outs of ``artefact`` and ``machine_file`` at the pose of ``pf``; ``margin_mm``
    is the clearance kept beyond keep-out + stylus radius (at least the safety standoff)."""
    rate = 1.0 / float((pf.jinv @ pf.spindle)[k])
    hz = [i for i in range(3) if i != k]
    rs = stylus_radius_mm
    pts, rad = [], []
    for b, c in zip(artefact.balls, balls_w, strict=True):
        pts.append(c)
        rad.append(b.diameter_mm / 2 + rs + margin_mm)
        foot = c - np.array([0.0, 0.0, b.rod_length_mm])
        n = max(2, int(np.ceil(b.rod_length_mm / ROD_STEP_MM)) + 1)
        step = b.rod_length_mm / (n - 1)
        rho = b.rod_diameter_mm / 2 + rs + margin_mm
        for s in np.linspace(0.0, 1.0, n):
            pts.append(foot + s * (c - foot))
            rad.append(float(np.hypot(rho, step / 2)))
    q = pf.solve(machine, np.array(pts), state)
    t = machine_file.table
    plane_w = np.array([[0.0, 0.0, t.surface_z_mm], [1.0, 0.0, t.surface_z_mm],
                        [0.0, 1.0, t.surface_z_mm]])
    qp = pf.solve(machine, plane_w, state)
    coef = np.linalg.lstsq(np.column_stack([np.ones(3), qp[:, hz]]), qp[:, k], rcond=None)[0]
    lift = (t.clearance_mm + rs + margin_mm) / rate
    # the table's highest point along the spindle: its rim towards the spindle's lean
    u_w = pf.r_fw.T @ pf.spindle
    v = u_w - u_w[2] * np.array([0.0, 0.0, 1.0])
    nv = float(np.linalg.norm(v))
    rim_w = np.array([0.0, 0.0, t.surface_z_mm]) + (t.radius_mm * v / nv if nv > 1e-12 else 0.0)
    rim = float(pf.solve(machine, rim_w[None, :], state)[0, k]) + lift
    boxes = []
    for box in machine_file.keep_out:
        lo, hi = np.array(box.min_mm), np.array(box.max_mm)
        corners = np.array(np.meshgrid(*zip(lo, hi, strict=True))).T.reshape(-1, 3)
        qc = pf.solve(machine, corners, state)
        grow = t.clearance_mm + rs + margin_mm
        top = qc[:, k].max() if rate > 0 else qc[:, k].min()
        boxes.append((qc[:, hz].min(axis=0) - grow, qc[:, hz].max(axis=0) + grow,
                      float(top + (t.clearance_mm + rs + margin_mm) / rate)))
    return PoseHeights(k, rate, hz, q[:, hz], q[:, k], np.array(rad), coef,
                       float(np.linalg.norm(coef[1:])) * (rs + margin_mm), lift, rim, boxes)
