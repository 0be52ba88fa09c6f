"""Candidate poses of ``rumba plan`` and what a visit of each costs in machine time.

A candidate is a B/C indexation of a grid within the machine's travel. It is admitted only when
its one-pose program (every ball, the plan's probing) builds and passes ``programs.safety``
(travel, keep-outs, stem, clearance) — checked lazily, when a design first picks the pose, and
cached. Its in-pose time (first approach to last retract) comes from the cycle-time model of
that program; until then a surrogate stands in: the rapid time of the ball tour at that pose
(horizontal open tour + the rise and fall between balls along the spindle) plus a constant
calibrated on the poses already built. Between two visits: the index (the larger rotary move at
``rotary_rapid_deg_min`` + ``rotary_clamp_s``), the retract to the height the rotary sweep needs
(``programs.geometry.sweep_required`` on a 2° grid, as the tool path does) and the rapid to the
next pose's first ball.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from contracts.messages import TOUCH_DIRECTIONS
from contracts.setup_files import MachineFile, Plan, PoseFile
from contracts.touch_frame import rotation_z_to
from identification.kinematics import ChainState, Machine, frames, to_model
from identification.model import Artefact
from programs.cycletime import estimate
from programs.geometry import (
    SWEEP_STEP_DEG,
    ProgramError,
    pose_frame,
    retract_axis,
    sweep_required,
)
from programs.model import Targets, ball_positions
from programs.safety import SafetyError, check_program
from programs.tilted import head_tilts, park_value
from programs.toolpath import APPROACH_GAP_MM, build_program, clearance_margin


@dataclass(frozen=True)
class Visit:
    """One candidate's one-pose program: admitted or why not, and its in-pose part."""

    ok: bool
    reason: str = ""
    t_in_s: float = 0.0  # first approach to last retract, cycle-time model
    entry: np.ndarray = field(default_factory=lambda: np.zeros(3))  # first corner, X Y Z
    exit: np.ndarray = field(default_factory=lambda: np.zeros(3))  # after the last retract


class Candidates:
    """The grid poses of one machine × artefact × plan probing, with lazy safety and costs."""

    def __init__(self, machine: Machine, machine_file: MachineFile, artefact: Artefact,
                 probing: Plan, two_speed: bool, poses: list[tuple[float, float]],
                 centres_mm: np.ndarray) -> None:
        self.machine, self.mf, self.artefact = machine, machine_file, artefact
        self.probing, self.two_speed, self.poses = probing, two_speed, poses
        self.visits: dict[int, Visit] = {}
        self.builds = 0
        r1, r2 = machine.rotary_axes
        # A head that tilts the spindle: its programs index at the park value of
        # the axis most along the spindle at the rotary home (programs.tilted)
        self.park = park_value(machine) if head_tilts(machine) else None
        if self.park is not None:
            self.k, value = self.park
            _lo, hi = machine.axes["XYZ"[self.k]].travel
            self.up = 1.0 if value == hi else -1.0
        else:
            pf = pose_frame(machine, {r1: poses[0][0], r2: poses[0][1]}, ChainState())
            self.k, rate = retract_axis(pf)
            self.up = 1.0 if rate > 0 else -1.0
        dyn = machine_file.dynamics
        self.rapid_s_per_mm = 60.0 / dyn.rapid_mm_min
        self.proxy_s = self._tour_mm(np.asarray(centres_mm)) * self.rapid_s_per_mm
        self._sweep: dict[tuple, float] = {}
        self._costs: tuple[int, np.ndarray] | None = None

    def refuse_table(self) -> int:
        """Refuse, without building, the poses at which a point every program visits — the
        corners of a ball's equator square, its clearance points, the point over its pole —
        or the way down onto a corner lies in the table keep-out (the safety check would
        refuse the program); how many."""
        m, t, rs = self.machine, self.mf.table, self.probing.stylus_radius_mm
        rot = np.array(self.poses, float)
        n = len(rot)
        r1, r2 = m.rotary_axes
        zero = np.zeros(n)
        f_w, f_t = frames(m, to_model(m, {"X": zero, "Y": zero, "Z": zero, r1: rot[:, 0],
                                          r2: rot[:, 1]}), ChainState())
        spindle = np.einsum("nij,j->ni", f_t[:, :3, :3], np.asarray(m.spindle_axis, float))
        # the equator directions in the tool frame (programs.tilted; the X-Y diagonals where
        # the spindle is along z), per pose (n, 4, 3)
        d = np.array([[rotation_z_to(s) @ np.asarray(TOUCH_DIRECTIONS[k], float)
                       for k in (1, 2, 3, 4)] for s in spindle])
        refused = 0
        for b, c_w in zip(self.artefact.balls, self.artefact.nominal_mm, strict=True):
            a = b.diameter_mm / 2 + rs + self.probing.standoff_mm + APPROACH_GAP_MM
            rel = np.concatenate([-d * a * np.sqrt(2), -d * a,
                                  (spindle * a)[:, None, :]], axis=1)  # foundation frame
            tip = c_w + np.einsum("nji,nkj->nki", f_w[:, :3, :3], rel)
            z_k, r_k = t.surface_z_mm + t.clearance_mm + rs, t.radius_mm + t.clearance_mm + rs
            inside = (tip[..., 2] < z_k) & (np.hypot(tip[..., 0], tip[..., 1]) < r_k)
            # a ball is entered from above one of its corners: if that line, up along the
            # spindle, pierces the table for all four (a table tilted past 90° hanging over
            # the ball), nothing reaches it
            u_w = np.einsum("nji,nj->ni", f_w[:, :3, :3], spindle)
            down = u_w[:, None, 2] < -1e-9
            corner = tip[:, :4]
            s = np.where(down, (z_k - corner[..., 2]) / np.where(down, u_w[:, None, 2], -1.0),
                         -1.0)
            hit = corner[..., :2] + s[..., None] * u_w[:, None, :2]
            blocked = ((s >= 0) & (np.hypot(hit[..., 0], hit[..., 1]) < r_k)).all(axis=1)
            for i in np.flatnonzero(inside.any(axis=1) | blocked):
                if int(i) not in self.visits:
                    refused += 1
                    self.visits[int(i)] = Visit(False, f"ball {b.id}'s probing square enters "
                                                "the table keep-out")
        return refused

    # ------------------------------------------------------------------ one pose
    def visit(self, i: int) -> Visit:
        """Build and check candidate ``i``'s one-pose program (cached)."""
        if i not in self.visits:
            self.visits[i] = self._build(i)
        return self.visits[i]

    def _build(self, i: int) -> Visit:
        b, c = self.poses[i]
        plan = self.probing.model_copy(update={"poses": [PoseFile(b_deg=b, c_deg=c)],
                                               "drift_check": False, "repeats": 1})
        self.builds += 1
        try:
            prog = build_program(self.machine, self.mf, self.artefact, plan,
                                 two_speed=self.two_speed)
            check_program(prog)
        except (ProgramError, SafetyError) as e:
            return Visit(False, str(e))
        moves = [mv for mv in prog.moves if mv.kind != "dwell"]
        # moves[0..2]: retract to the travel end, index, rapid over the first ball (from the
        # unknown start: not timed); moves[3]: down to the first corner; moves[-1]: back up
        down, last = np.array(moves[3].target[:3]), np.array(moves[-2].target[:3])
        top_mm = abs(moves[-1].target[self.k] - last[self.k])
        descend_mm = float(np.linalg.norm(down - np.array(moves[2].target[:3])))
        t_in = estimate(prog).estimate_s - (top_mm + descend_mm) * self.rapid_s_per_mm
        return Visit(True, "", t_in, down, last)

    def cost_s(self, i: int) -> float:
        """In-pose seconds of candidate ``i``: exact once built, else the calibrated
        surrogate (rapid time of its ball tour + the median offset of the poses built)."""
        return float(self.costs()[i])

    def costs(self) -> np.ndarray:
        """``cost_s`` of every candidate (recomputed only when a pose was built)."""
        if self._costs is None or self._costs[0] != len(self.visits):
            built = [j for j, w in self.visits.items() if w.ok]
            off = float(np.median([self.visits[j].t_in_s - self.proxy_s[j] for j in built])) \
                if built else 0.0
            out = self.proxy_s + off
            for j in built:
                out[j] = self.visits[j].t_in_s
            self._costs = (len(self.visits), out)
        return self._costs[1]

    def _tour_mm(self, centres: np.ndarray) -> np.ndarray:
        """Shortest open tour through the ball centres (horizontal) + rise and fall along the
        spindle between them, per pose (N, n, 3): the geometry-dependent part of a visit."""
        hz = [a for a in range(3) if a != self.k]
        n = centres.shape[1]
        perms = np.array(list(itertools.permutations(range(n))) if n <= 6 else [range(n)])
        c = centres[:, perms]  # (N, perms, n, 3)
        step = np.diff(c, axis=2)
        mm = np.linalg.norm(step[..., hz], axis=-1).sum(-1) + 2 * np.abs(step[..., self.k]).sum(-1)
        return mm.min(axis=1)

    # -------------------------------------------------------------- between poses
    def sweep_height(self, a: tuple[float, float], b: tuple[float, float]) -> float:
        """Retract value clearing everything while indexing from pose a to pose b (grid of
        the tool path's spacing over the rotary rectangle, cached)."""
        if self.park is not None:  # a tilting head indexes at the park value
            return self.park[1]
        key = (a, b) if a <= b else (b, a)
        if key not in self._sweep:
            g1 = _grid(a[0], b[0])
            g2 = _grid(a[1], b[1])
            u, v = np.meshgrid(g1, g2, indexing="ij")
            balls_w = ball_positions(self.artefact, Targets())
            # the same margin as the tool path: stylus radius + the plan's clearance margin
            margin = self.probing.stylus_radius_mm + clearance_margin(
                self.probing, self.probing.standoff_mm)
            z = sweep_required(self.machine, self.mf, self.artefact, balls_w, ChainState(),
                               self.k,
                               u.ravel(), v.ravel(), margin)
            self._sweep[key] = float(z.max() if self.up > 0 else z.min()) + self.up * 1.0
        return self._sweep[key]

    def transition_s(self, pa: tuple[float, float], va: Visit, pb: tuple[float, float],
                     vb: Visit) -> float:
        """Seconds from the last retract at pose a to the first corner at pose b."""
        dyn = self.mf.dynamics
        delta = max(abs(pb[0] - pa[0]), abs(pb[1] - pa[1]))
        index = delta / dyn.rotary_rapid_deg_min * 60.0 + dyn.rotary_clamp_s if delta > 0 \
            else 0.0
        h = self.sweep_height(pa, pb) if delta > 0 else -self.up * np.inf
        top = max(h * self.up, va.exit[self.k] * self.up) * self.up
        hz = [a for a in range(3) if a != self.k]
        mm = (abs(top - va.exit[self.k]) + float(np.linalg.norm(va.exit[hz] - vb.entry[hz]))
              + abs(top - vb.entry[self.k]))
        return index + mm * self.rapid_s_per_mm


def _grid(x0: float, x1: float) -> np.ndarray:
    n = max(2, int(np.ceil(abs(x1 - x0) / SWEEP_STEP_DEG)) + 1)
    return np.linspace(x0, x1, n)
