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
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from identification.kinematics import frames, to_model
from programs.geometry import tip_affine
from programs.toolpath import Program, ball_positions, chain_state

INDEX_STEP_DEG = 0.5
INDEX_MARGIN_MM = 0.05  # covers the sampling error of the index sweep
TOL_MM = 1e-6


class SafetyError(ValueError):
    """The program is unsafe; the message names block, pose, ball and reason in one line."""


@dataclass(frozen=True)
class SafetyReport:
    moves: int
    segments: int
    min_slack_mm: float  # smallest margin beyond the required clearance (non-probing moves)
    note: str = ""


def tip_in_workpiece(prog: Program, q: np.ndarray) -> np.ndarray:
    """Stylus-tip centre in the last workpiece frame for controller states q (N, 5).

    For fixed rotary joints the chain is affine in the linear axes (no motion errors here), so
    each distinct rotary state costs four chain evaluations and every point one product."""
    a, b, inv = _affine(prog, q[:, 3:5])
    return b[inv] + np.einsum("ni,nij->nj", q[:, :3], a[inv])


def _affine(prog: Program, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    uniq, inv = np.unique(rot, axis=0, return_inverse=True)
    cache: dict = prog.__dict__.setdefault("_affine_cache", {})  # per rotary state
    missing = [r for r in map(tuple, uniq) if r not in cache]
    if missing:
        a, b = tip_affine(prog.machine, prog.state, np.array(missing, float))
        for r, aa, bb in zip(missing, a, b, strict=True):
            cache[r] = (aa, bb)
    a = np.array([cache[r][0] for r in map(tuple, uniq)])
    b = np.array([cache[r][1] for r in map(tuple, uniq)])
    return a, b, inv.reshape(-1)


def _tip_exact(prog: Program, q: np.ndarray) -> np.ndarray:
    m, state = prog.machine, prog.state
    qm = to_model(m, {a: q[:, i] for i, a in enumerate(prog.axis_letters)}, state.linear_scale)
    f_w, f_t = frames(m, qm, state)
    tip = np.asarray(m.tool_tip_mm, float) + state.tip_offset_mm
    tip_f = np.einsum("nij,j->ni", f_t[:, :3, :3], tip) + f_t[:, :3, 3]
    return np.einsum("nji,nj->ni", f_w[:, :3, :3], tip_f - f_w[:, :3, 3])


def stem_direction(prog: Program, rot: np.ndarray) -> np.ndarray:
    """Unit spindle direction (tip → spindle) in the last workpiece frame per rotary state."""
    m = prog.machine
    n = len(rot)
    qm = to_model(m, {"X": np.zeros(n), "Y": np.zeros(n), "Z": np.zeros(n),
                      prog.rotary[0]: rot[:, 0], prog.rotary[1]: rot[:, 1]})
    f_w, f_t = frames(m, qm, prog.state)
    u = np.einsum("nij,j->ni", f_t[:, :3, :3], np.asarray(m.spindle_axis, float))
    return np.einsum("nji,nj->ni", f_w[:, :3, :3], u)


def _r_fw(prog: Program, rot: np.ndarray) -> np.ndarray:
    """Rotation foundation ← last workpiece frame for rotary states (N, 2)."""
    m = prog.machine
    n = len(rot)
    qm = to_model(m, {"X": np.zeros(n), "Y": np.zeros(n), "Z": np.zeros(n),
                      prog.rotary[0]: rot[:, 0], prog.rotary[1]: rot[:, 1]})
    return frames(m, qm, prog.state)[0][:, :3, :3]


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
        if mv.kind == "probe" and mv.feed_mm_min > dyn.max_probe_feed_mm_min:
            raise SafetyError(f"{_where(prog, i)}: probing feed {mv.feed_mm_min:g} mm/min exceeds "
                              f"dynamics.max_probe_feed_mm_min {dyn.max_probe_feed_mm_min:g}")
        if mv.kind in ("feed", "retract") and mv.feed_mm_min > dyn.max_feed_mm_min:
            raise SafetyError(f"{_where(prog, i)}: feed {mv.feed_mm_min:g} mm/min exceeds "
                              f"dynamics.max_feed_mm_min {dyn.max_feed_mm_min:g}")
        if mv.kind in ("feed", "probe") and mv.feed_mm_min <= 0:
            raise SafetyError(f"{_where(prog, i)}: feed must be positive")
        for j, a in enumerate(letters):
            v = mv.target[j]
            lo, hi = m.axes[a].travel
            if not math.isnan(v) and not lo - TOL_MM <= v <= hi + TOL_MM:
                unit = "mm" if j < 3 else "deg"
                raise SafetyError(f"{_where(prog, i)}: {a}{v:.4f} is outside the {a} travel "
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
                raise SafetyError(f"{_where(prog, i)}: rotary and linear axes in one block")
            index_moves.append((i, np.array(prev, float), np.array(cur, float)))
        elif not any(math.isnan(prev[k]) for k in range(3)):
            segs_a.append(prev)
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
        raise SafetyError(f"{_where(prog, int(owner[j]))}: {reason}")

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
    for j in np.nonzero((own >= 0) & dog)[0]:
        c = balls_w[own[j]]
        if _seg_point(pa[j][None], pb[j][None], c[None])[0] < np.linalg.norm(pa[j] - c) - TOL_MM:
            fail(j, "a non-linear rapid of this retract would cut into the ball")
    slack, explain = keepout_slack(prog, pa, pb, own, stem_direction(prog, qa[:, 3:5]))
    bad = np.nonzero(slack < 0)[0]
    if bad.size:
        fail(bad[0], explain(int(bad[0])))
    return float(slack[kinds != "probe"].min(initial=math.inf))


def keepout_slack(prog: Program, pa: np.ndarray, pb: np.ndarray, own: np.ndarray,
                  stem: np.ndarray | None = None) -> tuple[np.ndarray, Callable[[int], str]]:
    """Slack (mm, < 0 = violation) of tip segments pa→pb (workpiece frame) against every keep-out,
    and a function giving the reason for segment j's tightest one. ``own`` is the ball index a
    probing or retract segment may touch (its sphere is exempt, its rod has no standoff margin),
    or -1. ``stem`` (N, 3): unit spindle direction in the workpiece frame; the stylus stem (a
    cylinder of ``plan.stylus_length_mm`` from the tip) then sweeps a parallelogram per segment
    that must keep the standoff from every ball and rod (own ball and rod exempt on probing
    lines). All balls are handled in one vectorised pass (segments × balls)."""
    plan, art, mf = prog.plan, prog.artefact, prog.machine_file
    rs, standoff = plan.stylus_radius_mm, prog.standoff_mm
    balls_w = ball_positions(art, prog.targets)
    n, nb = len(pa), len(art.balls)
    r_ball = np.array([b.diameter_mm / 2 for b in art.balls])
    r_rod = np.array([b.rod_diameter_mm / 2 for b in art.balls])
    top = balls_w - np.column_stack([np.zeros((nb, 2)),
                                     np.sqrt(np.maximum(r_ball**2 - r_rod**2, 0.0))])
    bot = balls_w - np.column_stack([np.zeros((nb, 2)),
                                     [b.rod_length_mm for b in art.balls]])
    # (nb·n) pairs: ball k varies slowest
    tile = lambda x: np.tile(x, (nb, 1))  # noqa: E731
    rep = lambda x: np.repeat(x, n, axis=0)  # noqa: E731
    pa_k, pb_k, c_k, top_k, bot_k = tile(pa), tile(pb), rep(balls_w), rep(top), rep(bot)
    is_own = (np.tile(own, nb) == np.repeat(np.arange(nb), n)).reshape(nb, n)
    kinds: list[tuple[str, np.ndarray]] = []  # (reason template, gap (nb, n))
    slacks: list[np.ndarray] = []

    gap = (_seg_point(pa_k, pb_k, c_k).reshape(nb, n) - (r_ball + rs)[:, None])
    slacks.append(np.where(is_own, np.inf, gap - standoff + TOL_MM))
    kinds.append(("stylus comes {gap:.3f} mm from ball {ball} (keep-out: ball + stylus radius "
                  f"+ standoff {standoff:g} mm)", gap))
    gap = _seg_seg(pa_k, pb_k, top_k, bot_k).reshape(nb, n) - (r_rod + rs)[:, None]
    slacks.append(gap - np.where(is_own, 0.0, standoff) + TOL_MM)
    kinds.append(("stylus comes {gap:.3f} mm from the rod of ball {ball}", gap))
    if stem is not None:
        e2 = tile(stem * plan.stylus_length_mm)
        e1 = pb_k - pa_k
        r_st = plan.stem_radius_mm
        gap = _point_par(c_k, pa_k, e1, e2).reshape(nb, n) - r_ball[:, None] - r_st
        slacks.append(np.where(is_own, np.inf, gap - standoff + TOL_MM))
        kinds.append(("stylus stem comes {gap:.3f} mm from ball {ball}", gap))
        gap = _seg_par(top_k, bot_k, pa_k, e1, e2).reshape(nb, n) - r_rod[:, None] - r_st
        slacks.append(np.where(is_own, np.inf, gap - standoff + TOL_MM))
        kinds.append(("stylus stem comes {gap:.3f} mm from the rod of ball {ball}", gap))
    t = mf.table
    hit = _below_disc(pa, pb, t.surface_z_mm + t.clearance_mm + rs,
                      t.radius_mm + t.clearance_mm + rs)
    slacks.append(np.where(hit, -1.0, np.inf)[None, :])
    kinds.append((f"stylus enters the table keep-out (surface z {t.surface_z_mm:g} + clearance "
                  f"{t.clearance_mm:g} mm, radius {t.radius_mm:g} mm)", np.zeros((1, n))))
    for box in mf.keep_out:
        grow = rs + t.clearance_mm
        lo, hi = np.array(box.min_mm) - grow, np.array(box.max_mm) + grow
        slacks.append(np.where(_seg_box(pa, pb, lo, hi), -1.0, np.inf)[None, :])
        kinds.append((f"stylus enters keep-out box {box.name}", np.zeros((1, n))))
    every = np.concatenate(slacks, axis=0)  # (rows, n)
    row_kind = np.concatenate([np.full(len(x), i) for i, x in enumerate(slacks)])
    row_ball = np.concatenate([np.arange(len(x)) for x in slacks])
    tight = np.argmin(every, axis=0)

    def explain(j: int) -> str:
        r = int(tight[j])
        template, gaps = kinds[row_kind[r]]
        k = int(row_ball[r])
        return template.format(gap=gaps[k, j], ball=art.balls[k].id if nb else "")

    return every[tight, np.arange(n)], explain


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
                raise SafetyError(
                    f"{_where(prog, i)}: rotary index passes {r1}{b_s[j]:.1f} {r2}{c_s[j]:.1f} "
                    f"with the stylus {gap[j]:.3f} mm below the top of {name} (retract first)")


def _grid(a: float, b: float) -> np.ndarray:
    return np.linspace(a, b, max(2, math.ceil(abs(b - a) / INDEX_STEP_DEG) + 1))


# ------------------------------------------------------------------ vectorised distance helpers


def _seg_point(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    ab = b - a
    L2 = np.einsum("ij,ij->i", ab, ab)
    t = np.where(L2 > 0, np.einsum("ij,ij->i", p - a, ab) / np.where(L2 > 0, L2, 1), 0.0)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * ab - p, axis=1)


def _point_par(c: np.ndarray, p0: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Distance from points c to parallelograms p0 + s·e1 + t·e2 (s, t in [0, 1])."""
    edges = [(p0, p0 + e1), (p0 + e2, p0 + e1 + e2), (p0, p0 + e2), (p0 + e1, p0 + e1 + e2)]
    d = np.min([_seg_point(a, b, c) for a, b in edges], axis=0)
    n = np.cross(e1, e2)
    nn = np.linalg.norm(n, axis=1)
    ok = nn > 1e-9 * np.maximum(np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-300)
    if ok.any():
        w = c[ok] - p0[ok]
        g = np.stack([e1[ok], e2[ok]], axis=2)  # (M, 3, 2)
        st = np.linalg.solve(np.einsum("mki,mkj->mij", g, g),
                             np.einsum("mki,mk->mi", g, w)[..., None])[..., 0]
        inside = np.all((st >= 0) & (st <= 1), axis=1)
        perp = np.abs(np.einsum("mi,mi->m", w, n[ok])) / nn[ok]
        dd = d[ok]
        dd[inside] = np.minimum(dd[inside], perp[inside])
        d[ok] = dd
    return d


def _seg_par(r0: np.ndarray, r1: np.ndarray, p0: np.ndarray, e1: np.ndarray,
             e2: np.ndarray) -> np.ndarray:
    """Distance from segments r0→r1 to parallelograms p0 + s·e1 + t·e2: the closer of the
    segment to the four edges and its end points to the face, 0 where it pierces the face."""
    edges = [(p0, p0 + e1), (p0 + e2, p0 + e1 + e2), (p0, p0 + e2), (p0 + e1, p0 + e1 + e2)]
    d = np.min([_seg_seg(r0, r1, a, b) for a, b in edges]
               + [_point_par(r0, p0, e1, e2), _point_par(r1, p0, e1, e2)], axis=0)
    m = np.stack([e1, e2, r0 - r1], axis=2)  # p0 + s e1 + t e2 = r0 + w (r1 - r0)
    det = np.linalg.det(m)
    ok = np.abs(det) > 1e-9
    if ok.any():
        x = np.linalg.solve(m[ok], (r0 - p0)[ok][..., None])[..., 0]
        pierce = np.all((x >= 0) & (x <= 1), axis=1)
        dd = d[ok]
        dd[pierce] = 0.0
        d[ok] = dd
    return d


def _seg_seg(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Closest distance between segments p1q1 and p2q2 (Ericson, Real-Time Collision Detection
    §5.1.9), vectorised."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = np.einsum("ij,ij->i", d1, d1)
    e = np.einsum("ij,ij->i", d2, d2)
    f = np.einsum("ij,ij->i", d2, r)
    c = np.einsum("ij,ij->i", d1, r)
    b = np.einsum("ij,ij->i", d1, d2)
    denom = a * e - b * b
    eps = 1e-12
    s = np.where(denom > eps, np.clip((b * f - c * e) / np.where(denom > eps, denom, 1), 0, 1), 0.0)
    s = np.where(a <= eps, 0.0, s)
    t = np.where(e > eps, (b * s + f) / np.where(e > eps, e, 1), 0.0)
    t_c = np.clip(t, 0.0, 1.0)
    s = np.where((t != t_c) & (a > eps), np.clip((b * t_c - c) / np.where(a > eps, a, 1), 0, 1), s)
    c1 = p1 + s[:, None] * d1
    c2 = p2 + t_c[:, None] * d2
    return np.linalg.norm(c1 - c2, axis=1)


def _below_disc(pa: np.ndarray, pb: np.ndarray, z_thr: float, radius: float) -> np.ndarray:
    """Does the segment have a point with z < z_thr and radial distance < radius?"""
    dz = pb[:, 2] - pa[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        tz = (z_thr - pa[:, 2]) / dz
    lo = np.where(dz > 0, 0.0, np.where(dz < 0, tz, 0.0))
    hi = np.where(dz > 0, tz, np.where(dz < 0, 1.0, 1.0))
    flat_below = (dz == 0) & (pa[:, 2] < z_thr)
    lo = np.where(dz == 0, np.where(flat_below, 0.0, 1.0), np.clip(lo, 0, 1))
    hi = np.where(dz == 0, np.where(flat_below, 1.0, 0.0), np.clip(hi, 0, 1))
    has = (hi > lo) | flat_below
    # minimum radial distance on [lo, hi] (quadratic in t)
    a2 = pa[:, :2]
    d2 = pb[:, :2] - pa[:, :2]
    dd = np.einsum("ij,ij->i", d2, d2)
    tstar = np.where(dd > 0, -np.einsum("ij,ij->i", a2, d2) / np.where(dd > 0, dd, 1), 0.0)
    tstar = np.clip(tstar, lo, np.maximum(lo, hi))
    rmin = np.linalg.norm(a2 + tstar[:, None] * d2, axis=1)
    return has & (rmin < radius)


def _seg_box(pa: np.ndarray, pb: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Slab test: does the segment intersect the axis-aligned box?"""
    d = pb - pa
    t0 = np.zeros(len(pa))
    t1 = np.ones(len(pa))
    for k in range(3):
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (lo[k] - pa[:, k]) / d[:, k]
            tb = (hi[k] - pa[:, k]) / d[:, k]
        par = d[:, k] == 0
        inside = (pa[:, k] >= lo[k]) & (pa[:, k] <= hi[k])
        t0 = np.where(par, np.where(inside, t0, 2.0), np.maximum(t0, np.minimum(ta, tb)))
        t1 = np.where(par, np.where(inside, t1, -1.0), np.minimum(t1, np.maximum(ta, tb)))
    return t0 <= t1
