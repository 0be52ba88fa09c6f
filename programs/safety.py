"""Pre-release check: simulate a program's tool path on the machine model against travel limits,
feed bounds and keep-out volumes (ball + rod per ball, the table, configured boxes).

The moving objects are the stylus tip sphere (radius = stylus radius) and its stem (a cylinder of
``plan.stylus_length_mm`` along the spindle, which sweeps a parallelogram per move, checked
against balls and rods; the probe body beyond it is not modelled). For fixed rotary joints the
tip position in the last workpiece frame is affine in the controller linear axes, so every linear
move is an exact segment there; rapids that move several axes are also checked as every
axis-by-axis "dog-leg" (a non-linear rapid stays on or between those). Rotary index moves are
sampled (0.5°) over the rectangle of both rotary ranges and must keep the tip above every
keep-out along the spindle (error between samples ≤ R·h²/8 < 0.01 mm, covered by a margin).
Probing moves may enter their own ball's envelope only along their probing line, no further
than the configured overtravel; retracts leave it along the same line.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from identification.kinematics import frames, to_model
from programs.bodies import body_slack
from programs.clearance import TOL_MM, keepout_slack, seg_point, tip_in_workpiece
from programs.model import Program, ball_positions, chain_state

INDEX_STEP_DEG = 0.5
INDEX_MARGIN_MM = 0.05  # covers the sampling error of the index sweep


class SafetyError(ValueError):
    """The program is unsafe; the message names block, pose, ball and reason in one line.
    ``pose``: the plan's pose index of the offending move, None when the plan as a whole is
    at fault (so a planner can drop that pose and try again)."""

    def __init__(self, message: str, pose: int | None = None) -> None:
        super().__init__(message)
        self.pose = pose


def _unsafe(prog: Program, i: int, reason: str) -> SafetyError:
    """The error for move ``i``: where it is (``_where``), why, and its pose index."""
    p = prog.moves[i].pose
    return SafetyError(f"{_where(prog, i)}: {reason}",
                       p if 0 <= p < len(prog.plan.poses) else None)


@dataclass(frozen=True)
class SafetyReport:
    moves: int
    segments: int
    # smallest margin beyond the required standoff/clearance of the non-probing moves to
    # everything but the ball each works on (whose standoff they reach by construction)
    min_slack_mm: float
    note: str = ""


def _rotary_frames(prog: Program, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Workpiece and tool frames at zero linear axes for rotary states (N, 2)."""
    m = prog.machine
    n = len(rot)
    qm = to_model(m, {"X": np.zeros(n), "Y": np.zeros(n), "Z": np.zeros(n),
                      prog.rotary[0]: rot[:, 0], prog.rotary[1]: rot[:, 1]})
    return frames(m, qm, prog.state)


def stem_direction(prog: Program, rot: np.ndarray) -> np.ndarray:
    """Unit spindle direction (tip → spindle) in the last workpiece frame per rotary state."""
    f_w, f_t = _rotary_frames(prog, rot)
    u = np.einsum("nij,j->ni", f_t[:, :3, :3], np.asarray(prog.machine.spindle_axis, float))
    return np.einsum("nji,nj->ni", f_w[:, :3, :3], u)


def _r_fw(prog: Program, rot: np.ndarray) -> np.ndarray:
    """Rotation foundation ← last workpiece frame for rotary states (N, 2)."""
    return _rotary_frames(prog, rot)[0][:, :3, :3]


def _where(prog: Program, i: int) -> str:
    mv = prog.moves[i]
    pose = prog.plan.poses[mv.pose] if 0 <= mv.pose < len(prog.plan.poses) else None
    r1, r2 = prog.rotary
    s = f"block N{mv.block} ({mv.kind})"
    if pose is not None:
        s += f", pose {mv.pose} ({r1}{pose.b_deg:g} {r2}{pose.c_deg:g})"
    if mv.ball:
        s += f", ball {mv.ball}"
    if mv.touch is not None:
        s += f", touch {mv.touch.id.touch} (seq {mv.touch.id.seq})"
    return s


def check_program(prog: Program) -> SafetyReport:
    """Raise ``SafetyError`` on the first unsafe block; return a summary otherwise."""
    plan, mf, m = prog.plan, prog.machine_file, prog.machine
    dyn = mf.dynamics
    moves = prog.moves
    letters = prog.axis_letters
    # -------- bounds from configuration
    if prog.overtravel_mm > plan.overtravel_mm + TOL_MM:
        raise SafetyError(f"overtravel {prog.overtravel_mm} mm exceeds the plan's "
                          f"{plan.overtravel_mm} mm")
    for i, mv in enumerate(moves):
        if mv.kind == "probe" and max(mv.feed_mm_min, mv.locate_feed_mm_min) > \
                dyn.max_probe_feed_mm_min:
            f = max(mv.feed_mm_min, mv.locate_feed_mm_min)
            raise _unsafe(prog, i, f"probing feed {f:g} mm/min exceeds "
                                   f"dynamics.max_probe_feed_mm_min {dyn.max_probe_feed_mm_min:g}")
        if mv.locate_feed_mm_min > 0 and not 0 < mv.backoff_mm < prog.standoff_mm:
            raise _unsafe(prog, i, f"two-speed touch backs off {mv.backoff_mm:g} "
                                   f"mm: expected more than 0 and less than the standoff "
                                   f"{prog.standoff_mm:g} mm")
        if mv.kind in ("feed", "retract") and mv.feed_mm_min > dyn.max_feed_mm_min:
            raise _unsafe(prog, i, f"feed {mv.feed_mm_min:g} mm/min exceeds "
                                   f"dynamics.max_feed_mm_min {dyn.max_feed_mm_min:g}")
        if mv.kind in ("feed", "probe") and mv.feed_mm_min <= 0:
            raise _unsafe(prog, i, "feed must be positive")
        for j, a in enumerate(letters):
            v = mv.target[j]
            lo, hi = m.axes[a].travel
            if not math.isnan(v) and not lo - TOL_MM <= v <= hi + TOL_MM:
                unit = "mm" if j < 3 else "deg"
                raise _unsafe(prog, i, f"{a}{v:.4f} is outside the {a} travel "
                                       f"[{lo:g}, {hi:g}] {unit}")
    if plan.stem_radius_mm >= plan.stylus_radius_mm:
        raise SafetyError(f"stylus stem diameter {2 * plan.stem_radius_mm:g} mm is not below the "
                          f"stylus ball diameter {plan.stylus_diameter_mm:g} mm")
    for t in prog.touches:
        ball = prog.artefact.balls[t.ball_number - 1]
        if prog.overtravel_mm >= ball.diameter_mm / 2:
            raise SafetyError(f"ball {ball.id}: overtravel {prog.overtravel_mm} mm reaches the "
                              "ball centre region")
    # -------- linear moves as segments (plus dog-legs for multi-axis rapids)
    segs_a, segs_b, owner, dog = [], [], [], []
    index_moves = []
    prev = (math.nan,) * 5
    for i, mv in enumerate(moves):
        cur = mv.target
        if mv.kind == "dwell":
            prev = cur
            continue
        if any(not abs(cur[k] - prev[k]) <= 1e-12 for k in (3, 4)):
            if any(abs(cur[k] - prev[k]) > 1e-12 for k in range(3)):
                raise _unsafe(prog, i, "rotary and linear axes in one block")
            index_moves.append((i, np.array(prev, float), np.array(cur, float)))
        elif not any(math.isnan(prev[k]) for k in range(3)):
            segs_a.append(_backed_off(prev, cur, mv.backoff_mm) if mv.backoff_mm > 0 else prev)
            segs_b.append(cur)
            owner.append(i)
            dog.append(False)
            changed = [k for k in range(3) if abs(cur[k] - prev[k]) > 1e-12]
            if mv.kind in ("rapid", "retract") and mv.feed_mm_min == 0 and len(changed) > 1:
                for perm in itertools.permutations(changed):
                    p = list(prev)
                    for k in perm:
                        q = list(p)
                        q[k] = cur[k]
                        segs_a.append(tuple(p))
                        segs_b.append(tuple(q))
                        owner.append(i)
                        dog.append(True)
                        p = q
        prev = cur
    min_gap = math.inf
    if segs_a:
        min_gap = _check_segments(prog, np.array(segs_a), np.array(segs_b), np.array(owner),
                                  np.array(dog))
    _check_index(prog, index_moves)
    return SafetyReport(len(moves), len(segs_a), min_gap,
                        "the first index starts from the unknown pose at the retract limit")


def _backed_off(prev: tuple[float, ...], cur: tuple[float, ...], backoff_mm: float
                ) -> tuple[float, ...]:
    """Where a two-speed touch may back off to at most: ``backoff_mm`` behind its start (a
    latch at the very start), on its probing line — so the checked line starts there."""
    a, b = np.array(prev[:3], float), np.array(cur[:3], float)
    u = (b - a) / max(float(np.linalg.norm(b - a)), 1e-12)
    return (*map(float, a - backoff_mm * u), *prev[3:])


def _check_segments(prog: Program, qa: np.ndarray, qb: np.ndarray, owner: np.ndarray,
                    dog: np.ndarray) -> float:
    plan, art = prog.plan, prog.artefact
    rs = plan.stylus_radius_mm
    pa = tip_in_workpiece(prog, qa)
    pb = tip_in_workpiece(prog, qb)
    balls_w = ball_positions(art, prog.targets)
    kinds = np.array([prog.moves[i].kind for i in owner])
    own = np.array([(prog.moves[i].touch.ball_number - 1) if prog.moves[i].touch is not None
                    and prog.moves[i].kind in ("probe", "retract") else -1 for i in owner])
    standoff = prog.standoff_mm

    def fail(j: int, reason: str) -> None:
        raise _unsafe(prog, int(owner[j]), reason)

    # own-ball line checks for probing and retract moves (vectorised)
    line = np.nonzero((own >= 0) & ~dog)[0]
    if line.size:
        is_probe = kinds[line] == "probe"
        c = balls_w[own[line]]
        a_ = np.where(is_probe[:, None], pa[line], pb[line])  # outer end of the line
        b_ = np.where(is_probe[:, None], pb[line], pa[line])  # inner end
        r_env = np.array([art.balls[k].diameter_mm / 2 for k in own[line]]) + rs
        da = np.linalg.norm(a_ - c, axis=1)
        db = np.linalg.norm(b_ - c, axis=1)
        bad = np.nonzero(da < r_env + standoff - TOL_MM)[0]
        if bad.size:
            j = bad[0]
            fail(line[j], f"probing line starts {da[j] - r_env[j]:.3f} mm outside ball "
                          f"{art.balls[own[line[j]]].id}'s envelope (standoff {standoff:g} mm "
                          "required)")
        bad = np.nonzero(db < r_env - plan.overtravel_mm - TOL_MM)[0]
        if bad.size:
            j = bad[0]
            fail(line[j], f"probing move ends {r_env[j] - db[j]:.3f} mm inside ball "
                          f"{art.balls[own[line[j]]].id}'s envelope (overtravel limit "
                          f"{plan.overtravel_mm:g} mm)")
        # direction of the tool relative to the workpiece in the machine frame
        r_fw = _r_fw(prog, qa[line, 3:5])
        rel = np.einsum("nij,nj->ni", r_fw, pb[line] - pa[line])
        rel /= np.linalg.norm(rel, axis=1, keepdims=True)
        want = np.array([prog.moves[int(owner[j])].touch.direction for j in line])
        want = np.where(is_probe[:, None], want, -want)
        bad = np.nonzero(np.linalg.norm(rel - want, axis=1) > 1e-6)[0]
        if bad.size:
            j = bad[0]
            fail(line[j], f"moves along {np.round(rel[j], 6).tolist()}, not the probing "
                          f"direction {np.round(want[j], 6).tolist()}")
        # radial: the line passes through the ball centre
        ab = b_ - a_
        off = np.linalg.norm(np.cross(ab, c - a_), axis=1) / np.maximum(
            np.linalg.norm(ab, axis=1), 1e-12)
        bad = np.nonzero(off > 1e-6)[0]
        if bad.size:
            j = bad[0]
            fail(line[j], f"probing line misses the centre of ball "
                          f"{art.balls[own[line[j]]].id} by {off[j]:.4f} mm")
    # a dog-leg of a retract leaving its ball must only move away from the ball centre
    legs = np.nonzero((own >= 0) & dog)[0]
    if legs.size:
        c = balls_w[own[legs]]
        near = seg_point(pa[legs], pb[legs], c)
        start = np.array([np.linalg.norm(pa[j] - cj) for j, cj in zip(legs, c, strict=True)])
        bad = np.nonzero(near < start - TOL_MM)[0]
        if bad.size:
            fail(legs[bad[0]], "a non-linear rapid of this retract would cut into the ball")
    stem = stem_direction(prog, qa[:, 3:5])
    slack, explain = keepout_slack(prog, pa, pb, own, stem)
    bad = np.nonzero(slack < 0)[0]
    if bad.size:
        fail(bad[0], explain(int(bad[0])))
    # what moves with the head (probe body, spindle nose, housing), if declared
    slack, explain = body_slack(prog, pa, pb, stem)
    bad = np.nonzero(slack < 0)[0]
    if bad.size:
        fail(bad[0], explain(int(bad[0])))
    # The margin reported: non-probing moves against everything but the sphere of the ball
    # they work on — a move to a probing line's start ends on that sphere's standoff by
    # construction (margin 0 in every program), which the check above has enforced.
    ball_no = {b.id: k for k, b in enumerate(art.balls)}
    worked = np.array([ball_no.get(prog.moves[i].ball, -1) for i in owner])
    keep = kinds != "probe"
    margin, _ = keepout_slack(prog, pa[keep], pb[keep], own[keep], stem[keep], worked[keep])
    return float(margin.min(initial=math.inf)) - TOL_MM


def _check_index(prog: Program, index_moves: list) -> None:
    """Rotary moves: the tip must stay above every keep-out top along the spindle."""
    plan, art, mf, m = prog.plan, prog.artefact, prog.machine_file, prog.machine
    rs = plan.stylus_radius_mm
    balls_w = ball_positions(art, prog.targets)
    state = chain_state(prog.targets)
    for i, prev, cur in index_moves:
        lin = np.nan_to_num(cur[:3])  # heights do not depend on the horizontal axes
        if np.any(np.isnan(prev[3:])):
            b_s, c_s = np.array([cur[3]]), np.array([cur[4]])  # unknown start: target only
        else:
            gb = _grid(prev[3], cur[3])
            gc = _grid(prev[4], cur[4])
            bb, cc = np.meshgrid(gb, gc, indexing="ij")
            b_s, c_s = bb.ravel(), cc.ravel()
        n = b_s.size
        q = np.column_stack([np.broadcast_to(lin, (n, 3)), b_s, c_s])
        letters = prog.axis_letters
        qm = to_model(m, {a: q[:, j] for j, a in enumerate(letters)}, state.linear_scale)
        f_w, f_t = frames(m, qm, state)
        tip = np.asarray(m.tool_tip_mm, float) + state.tip_offset_mm
        tip_f = np.einsum("nij,j->ni", f_t[:, :3, :3], tip) + f_t[:, :3, 3]
        tip_w = np.einsum("nji,nj->ni", f_w[:, :3, :3], tip_f - f_w[:, :3, 3])
        spindle = np.einsum("nij,j->ni", f_t[:, :3, :3], np.asarray(m.spindle_axis, float))
        u = np.einsum("nji,nj->ni", f_w[:, :3, :3], spindle)
        h_tip = np.einsum("ni,ni->n", u, tip_w)
        tops: list[tuple[str, np.ndarray]] = []
        for k, b in enumerate(art.balls):
            c = balls_w[k]
            bot = c - np.array([0, 0, b.rod_length_mm])
            tops.append((f"ball {b.id}", u @ c + b.diameter_mm / 2 + prog.standoff_mm))
            tops.append((f"the rod of ball {b.id}",
                         np.maximum(u @ c, u @ bot) + b.rod_diameter_mm / 2 + prog.standoff_mm))
        t = mf.table
        uz = u[:, 2]
        h_table = t.surface_z_mm * uz + t.radius_mm * np.sqrt(np.clip(1 - uz**2, 0, 1))
        tops.append(("the table", h_table + t.clearance_mm))
        for box in mf.keep_out:
            corners = np.array(list(itertools.product(*zip(box.min_mm, box.max_mm, strict=True))))
            tops.append((f"keep-out box {box.name}", (u @ corners.T).max(axis=1) + t.clearance_mm))
        for name, h in tops:
            gap = h_tip - rs - h
            j = int(np.argmin(gap))
            if gap[j] < INDEX_MARGIN_MM:
                r1, r2 = prog.rotary
                raise _unsafe(
                    prog, i, f"rotary index passes {r1}{b_s[j]:.1f} {r2}{c_s[j]:.1f} "
                    f"with the stylus {gap[j]:.3f} mm below the top of {name} (retract first)")


def _grid(a: float, b: float) -> np.ndarray:
    return np.linspace(a, b, max(2, math.ceil(abs(b - a) / INDEX_STEP_DEG) + 1))
