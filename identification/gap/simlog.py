"""Touches of a probing run on a true machine with effects, vectorised, for the gap self-check.

The physics is the simulator's (simulators/truth.py, simulators/probe.py): the stylus sphere
moves along the programmed line (through the nominal ball centre, approach direction ``d`` in
controller X Y Z) and touches the true ball sphere through the true chain — links, tip setup and
the effects' motion errors — at ``|tip − ball| = R_ball + r_stylus``; the ball centre carries the
setup error and the effects' ball offsets at the touch time; the latched position adds the
effects' touch offsets and trigger noise along the approach direction. The contact is solved by
Newton on the line parameter for all touches at once (the self-check needs thousands of runs;
the G-code simulator's per-touch root finding is built for fidelity to a controller, not speed).
It lives here and not in simulators/ because identification must not import simulators.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.effects import Effect, EffectContext, combine_motion_errors
from identification.gap.data import TouchData
from identification.kinematics import (
    ChainState,
    Machine,
    rotary_columns,
    solve_centre,
    tip_minus_ball,
    to_model,
)
from identification.model import Artefact

DIAGONALS = np.array([[1, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]]) / np.sqrt(2.0)
_NEWTON = 8


@dataclass
class Truth:
    """The true machine: link errors (model units), setup errors (mm), effects with params."""

    links: dict[str, float] = field(default_factory=dict)
    ball_setup_mm: np.ndarray | None = None  # (n, 3) last workpiece frame
    tip_setup_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    effects: list[tuple[Effect, np.ndarray]] = field(default_factory=list)
    pose_offsets_mm: dict[int, np.ndarray] = field(default_factory=dict)  # outside the library
    # Per-visit index errors of the rotary axes, drawn N(0, σ) per pose (µrad 1σ by
    # axis letter; the true axis stops at command + δ), and ball steps — (ball index, time s,
    # displacement mm in the last workpiece frame): the ball sits there from that time on.
    index_std_urad: dict[str, float] = field(default_factory=dict)
    ball_steps: list[tuple[int, float, np.ndarray]] = field(default_factory=list)


@dataclass(frozen=True)
class Timing:
    touch_s: float = 6.0
    ball_s: float = 8.0
    pose_s: float = 25.0


def approach_directions(machine: Machine) -> np.ndarray:
    """(5, 3): four diagonals in the machine X-Y plane, then the pole along −spindle axis."""
    pole = -np.asarray(machine.spindle_axis, float)
    return np.vstack([DIAGONALS, pole / np.linalg.norm(pole)])


def index_errors_deg(machine: Machine, truth: Truth, n_poses: int, rng: np.random.Generator
                     ) -> np.ndarray:
    """(n_poses, 2) per-visit index errors (deg) of the two rotary axes, N(0, σ) each; zeros
    (and no draw) without ``index_std_urad``."""
    out = np.zeros((n_poses, 2))
    for k, a in enumerate(machine.rotary_axes[:2]):
        s = truth.index_std_urad.get(a, 0.0)
        if s > 0:
            out[:, k] = np.rad2deg(rng.normal(0.0, s * 1e-6, n_poses))
    return out


def simulate(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
             truth: Truth, stylus_radius_mm: float, noise_um: float, seed: int,
             timing: Timing = Timing(), standoff_mm: float = 2.0) -> TouchData:
    """One run: every pose, every ball, five touches, in that order."""
    rng = np.random.default_rng(seed)
    n_b = len(artefact.balls)
    dirs = approach_directions(machine)
    pose = np.repeat(np.arange(len(poses)), n_b * 5)
    ball = np.tile(np.repeat(np.arange(n_b), 5), len(poses))
    touch = np.tile(np.arange(1, 6), len(poses) * n_b)
    bc = np.asarray(poses, float)[pose]
    t = (np.arange(len(pose)) * timing.touch_s + pose * timing.pose_s
         + (pose * n_b + ball) * timing.ball_s)
    d = dirs[touch - 1]
    rot = rotary_columns(machine, bc[:, 0], bc[:, 1])
    true_bc = bc + index_errors_deg(machine, truth, len(poses), rng)[pose]
    nominal = artefact.nominal_mm[ball]
    centre_prog = solve_centre(machine, rot, nominal, ChainState())
    setup = np.zeros((n_b, 3)) if truth.ball_setup_mm is None else truth.ball_setup_mm
    w_true = nominal + setup[ball]
    rods = np.array([b.rod_length_mm for b in artefact.balls])[ball]
    ctx = EffectContext(t, bc[:, 0], bc[:, 1], ball, touch, d, centre_prog, w_true, rods)
    for eff, p in truth.effects:
        w_true = w_true + eff.ball_offset_mm(p, ctx)
    for b, t_step, v in truth.ball_steps:
        w_true = w_true + np.where(((ball == b) & (t >= t_step))[:, None], np.asarray(v), 0.0)
    state = ChainState(links=dict(truth.links), tip_offset_mm=np.asarray(truth.tip_setup_mm),
                       motion_errors=combine_motion_errors(
                           *[eff.motion_errors(p) for eff, p in truth.effects]))
    radius = np.array([b.diameter_mm / 2 for b in artefact.balls])[ball] + stylus_radius_mm
    start = centre_prog - (radius + standoff_mm)[:, None] * d
    rot_model = to_model(machine, rotary_columns(machine, true_bc[:, 0], true_bc[:, 1]))

    def gap(s: np.ndarray) -> np.ndarray:
        q = start + s[:, None] * d
        qm = to_model(machine, {k: q[:, i] for i, k in enumerate("XYZ")})
        return np.linalg.norm(tip_minus_ball(machine, {**qm, **rot_model}, w_true, state),
                              axis=1) - radius

    s = np.full(len(pose), standoff_mm)
    for _ in range(_NEWTON):
        f0 = gap(s)
        df = (gap(s + 1e-3) - f0) / 1e-3
        step = -f0 / df
        s = s + step
        if np.max(np.abs(step)) < 1e-10:
            break
    latched = start + s[:, None] * d
    ctx = EffectContext(t, bc[:, 0], bc[:, 1], ball, touch, d, latched, w_true, rods)
    for eff, p in truth.effects:
        latched = latched + eff.touch_offset_mm(p, ctx)
    for k, off in truth.pose_offsets_mm.items():
        latched[pose == k] += off
    latched = latched + rng.normal(0.0, noise_um * 1e-3, len(pose))[:, None] * d
    return TouchData(np.zeros(len(pose), int), pose, ball, touch, t, bc[:, 0], bc[:, 1], d,
                     latched)
