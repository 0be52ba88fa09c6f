"""The tool-path builder: touch targets and the moves of a plan × machine × artefact.

Geometry (METHOD.md §1): at every pose each ball is touched four times on its equator, approached
diagonally in the machine X-Y plane (``messages.TOUCH_DIRECTIONS`` 1-4) and once at the accessible
pole against the spindle axis. A touch is planned in *relative* coordinates ``r = tip − ball
centre`` (foundation frame, mm); for fixed rotary joints ``r`` is affine in the controller linear
axes (identification.kinematics.solve_centre), so ``q = q_centre + J⁻¹ r`` is exact and a straight
controller move is a straight relative move. The path: rapid to a corner of a square around the
ball (edges tangent to ball + stylus + standoff + approach gap, so square edges and radial moves are
rapids of one or two axes that stay clear even as non-linear "dog-leg" rapids), rapid in along the
probing line to the clearance point, feed the approach gap to the start point (standoff outside
ball + stylus radius), probe to the expected contact + overtravel, retract along the same line.
Heights are controller values of the retract axis (the one running along the spindle): before
every index the tool retracts above everything the rotary sweep can raise; between balls it
retracts only as high as the keep-out geometry demands on the way (``programs.heights``: exact
sphere profiles, rods along their length, the plan's clearance as the margin, never below the
standoff), the way in checked like every move and lifted to the pose's safe height if not clear;
after the pole touch it leaves the ball only as far as the clearance point. The four equator
touches are visited in the cheapest order around the square whose moves (checked with
``programs.clearance``'s keep-out test, stem included) are clear, an edge blocked by a neighbour
being lifted over it. With a two-speed plan on a dialect that can repeat a probing move, every
probing move locates fast, backs off ``BACKOFF_MM`` from the latch and re-touches slow.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence

import numpy as np

from contracts.messages import TOUCH_DIRECTIONS, TouchId
from contracts.setup_files import MAX_TOUCHES, SAFE_NAME, MachineFile, Plan, touch_count
from identification.kinematics import ChainState, Machine
from identification.model import Artefact
from programs.clearance import keepout_slack, tip_in_workpiece
from programs.geometry import (
    MAX_SWEEP_SAMPLES,
    PoseFrame,
    ProgramError,
    pose_frame,
    retract_axis,
    sweep_grid,
    sweep_required,
)
from programs.heights import pose_heights
from programs.model import (
    Program,
    Targets,
    Touch,
    ball_positions,
    chain_state,
    plan_visits,
)
from programs.moves import MoveBuilder, axes_only, seg_length, t3
from programs.tilted import build_tilted, spindle_is_tilted
from programs.tour import open_tour

APPROACH_GAP_MM = 0.5  # fed at approach feed between clearance and start point
ESTIMATE_STANDOFF_MM = 1.0  # standoff / overtravel cap when targets come from a last estimate
ESTIMATE_OVERTRAVEL_MM = 1.0
# Two-speed touch: back off this far from the fast latch before the slow re-touch. Measured from
# the latched point, not from where the axes stopped, so the deceleration past the contact does
# not matter; below APPROACH_GAP_MM, the back-off stays on the approach line already cleared.
BACKOFF_MM = 0.3
_SIDES = ((1, 2), (2, 3), (3, 4), (4, 1))  # the square's edges, by touch direction


def clearance_margin(plan: Plan, standoff_mm: float) -> float:
    """What transits and index retracts keep beyond keep-out + stylus radius: the plan's
    clearance, never less than the standoff the safety check demands."""
    return max(plan.clearance_mm, standoff_mm)


# ------------------------------------------------------------------------------- generator


def build_program(machine: Machine, machine_file: MachineFile, artefact: Artefact, plan: Plan,
                  targets: Targets | None = None, two_speed: bool = False) -> Program:
    """Generate the tool path of every repeat × pose × ball × touch. ``two_speed``: the
    dialect can repeat a probing move (``Dialect.two_speed``); with the plan's
    ``feeds.fast_probe_mm_min`` every touch then locates fast, backs off and re-touches slow."""
    targets = targets or Targets()
    n_touch = touch_count(plan, artefact)  # before anything is allocated
    if n_touch > MAX_TOUCHES:
        raise ProgramError(f"plan {plan.name}: {n_touch} touches, more than the ceiling of "
                           f"{MAX_TOUCHES} touches per program")
    for b in artefact.balls:
        if not SAFE_NAME.fullmatch(b.id):
            raise ProgramError(f"ball id {b.id!r} is not a safe name")
    est = targets.source == "estimate"
    standoff = min(plan.standoff_mm, ESTIMATE_STANDOFF_MM) if est else plan.standoff_mm
    overtravel = min(plan.overtravel_mm, ESTIMATE_OVERTRAVEL_MM) if est else plan.overtravel_mm
    if len(machine.rotary_axes) != 2:
        raise ProgramError(f"machine {machine.name}: needs two rotary axes")
    prog = Program(machine, machine_file, artefact, plan, targets, tuple(machine.rotary_axes),
                   2, standoff, overtravel)
    state = chain_state(targets)
    balls_w = ball_positions(artefact, targets)
    rs = plan.stylus_radius_mm
    clr = clearance_margin(plan, standoff)
    r1, r2 = prog.rotary

    frames_ = [pose_frame(machine, {r1: p.b_deg, r2: p.c_deg}, state) for p in plan.poses]
    if any(spindle_is_tilted(machine, pf) for pf in frames_):  # a head tilts it
        fast = plan.feeds.fast_probe_mm_min if two_speed else None
        return build_tilted(prog, frames_, fast, BACKOFF_MM)
    k_ret, rate = retract_axis(frames_[0])
    prog.retract_axis = k_ret
    sgn = 1.0 if rate > 0 else -1.0

    def sweep_height(a: tuple[float, float], b: tuple[float, float]) -> float:
        """Highest retract value over the rectangle of rotary values between two poses (any
        interpolation of a two-axis rotary rapid stays inside it)."""
        g1, g2 = sweep_grid(a[0], b[0]), sweep_grid(a[1], b[1])
        if len(g1) * len(g2) > MAX_SWEEP_SAMPLES:  # e.g. C -36000 → +36000 in one index
            raise ProgramError(f"index from {r1}{a[0]:g} {r2}{a[1]:g} to {r1}{b[0]:g} "
                               f"{r2}{b[1]:g}: {len(g1) * len(g2)} rotary samples, more than "
                               f"{MAX_SWEEP_SAMPLES}; add an intermediate pose")
        u, v = np.meshgrid(g1, g2, indexing="ij")
        z = sweep_required(machine, machine_file, artefact, balls_w, state, k_ret,
                           u.ravel(), v.ravel(), rs + clr)
        best = float(z.max() if sgn > 0 else z.min())
        return best + sgn * 1.0  # sampling margin (chord sag at 2° and 300 mm ≈ 0.05 mm)

    ax_lo, ax_hi = machine.axes["XYZ"[k_ret]].travel
    # The rotary pose at program start is unknown: retract to the end of travel first.
    z_start = ax_hi if sgn > 0 else ax_lo
    builder = MoveBuilder(prog, (math.nan, math.nan, math.nan, math.nan, math.nan))
    tgt: list[float | None] = [None] * 5
    tgt[k_ret] = z_start
    builder.emit("rapid", tgt, pose=0)
    prev_rot: tuple[float, float] | None = None
    seq = 0
    for rep, ip in plan_visits(plan):
        pose, pf = plan.poses[ip], frames_[ip]
        rot = (pose.b_deg, pose.c_deg)
        if prev_rot is not None and rot != prev_rot:
            z_idx = sweep_height(prev_rot, rot)
            if sgn * z_idx > sgn * builder.pos[k_ret]:
                tgt = [None] * 5
                tgt[k_ret] = z_idx
                builder.emit("rapid", tgt, pose=ip)
        if rot != prev_rot:
            builder.emit("rapid", [None, None, None, rot[0], rot[1]], pose=ip)
        prev_rot = rot
        k2, rate2 = retract_axis(pf)
        if k2 != k_ret or abs(rate2 - rate) > 1e-9:
            raise ProgramError(f"pose {ip}: the retract axis changes with the rotary pose")
        seq = _pose_touches(prog, builder, pf, ip, rep, seq, balls_w, state, two_speed,
                            lambda r=rot: sweep_height(r, r))
    tgt = [None] * 5
    tgt[k_ret] = z_start
    builder.emit("rapid", tgt, pose=ip)
    return prog



def _pose_touches(prog: Program, bld: MoveBuilder, pf: PoseFrame, ip: int, rep: int, seq: int,
                  balls_w: np.ndarray, state: ChainState, two_speed: bool,
                  z_safe: Callable[[], float]) -> int:
    """The touches of every ball at one pose. ``z_safe``: the retract value above every
    keep-out along the spindle at this pose (the fallback when a transit is not clear),
    computed only when a transit needs it."""
    machine, plan, artefact = prog.machine, prog.plan, prog.artefact
    k = prog.retract_axis
    heights = pose_heights(machine, prog.machine_file, artefact, balls_w, pf, state, k,
                           plan.stylus_radius_mm, clearance_margin(plan, prog.standoff_mm))
    higher, transit = heights.higher, heights.transit
    hz = heights.hz
    u_w = pf.r_fw.T @ pf.spindle  # stem direction in the workpiece frame
    centres = pf.solve(machine, balls_w, state)
    order = open_tour(centres[:, hz], np.array([bld.pos[i] for i in hz]))
    pose = plan.poses[ip]
    rot = (bld.pos[3], bld.pos[4])
    fast = plan.feeds.fast_probe_mm_min if two_speed else None

    def slack(path: list[tuple[np.ndarray, np.ndarray]],
              owns: Sequence[int] | None = None) -> np.ndarray:
        """Per move: keep-out slack of the straight move and, if it moves two axes, of both
        dog-legs (a non-linear rapid). ``owns``: ball a move may touch (radial moves), or -1."""
        p0 = np.array([seg[0] for seg in path], float)
        p1 = np.array([seg[1] for seg in path], float)
        qa, qb, parent = [p0], [p1], [np.arange(len(path))]
        changed = np.abs(p1 - p0) > 1e-12
        two = np.nonzero(changed.sum(axis=1) == 2)[0]
        axes = np.nonzero(changed[two])[1].reshape(-1, 2)  # the two axes, in order
        for first in axes.T:  # each dog-leg: one axis first, then the other
            mid = p0[two].copy()
            mid[np.arange(len(two)), first] = p1[two, first]
            qa += [p0[two], mid]
            qb += [mid, p1[two]]
            parent += [two, two]
        qa, qb, parent = np.concatenate(qa), np.concatenate(qb), np.concatenate(parent)

        def full(q: np.ndarray) -> np.ndarray:
            return np.column_stack([q, np.broadcast_to(rot, (len(q), 2))])
        pa, pb = tip_in_workpiece(prog, full(qa)), tip_in_workpiece(prog, full(qb))
        own = np.full(len(qa), -1) if owns is None else np.asarray(owns)[parent]
        sl = keepout_slack(prog, pa, pb, own, np.broadcast_to(u_w, pa.shape))[0]
        out = np.full(len(path), np.inf)
        np.minimum.at(out, parent, sl)
        return out

    def with_z(p: np.ndarray, z: float) -> np.ndarray:
        q = p.copy()
        q[k] = z
        return q

    def way_over(here: np.ndarray, corner: np.ndarray, z: float) -> list:
        """Up (or down) at ``here`` to z, then across to above the corner."""
        legs = [(here, with_z(here, z)), (with_z(here, z), with_z(corner, z))]
        return [(p0, p1) for p0, p1 in legs if np.linalg.norm(p1 - p0) > 1e-12]

    dirs = {tt: (np.asarray(TOUCH_DIRECTIONS[tt]) if tt < 5 else -pf.spindle)
            for tt in (1, 2, 3, 4, 5)}
    for tt in (1, 2, 3, 4):
        if order and abs(float(dirs[tt] @ pf.spindle)) > 1e-9:
            raise ProgramError(f"pose {ip}: equator directions are not ⊥ the spindle axis")

    def geometry(j: int) -> tuple:
        r_env = artefact.balls[j].diameter_mm / 2 + plan.stylus_radius_mm
        a = r_env + prog.standoff_mm + APPROACH_GAP_MM  # square half side (edges clear by gap)
        c = centres[j]

        def at(r: np.ndarray, _c: np.ndarray = c) -> np.ndarray:
            return _c + pf.jinv @ r

        corner = {tt: at(-dirs[tt] * a * math.sqrt(2)) for tt in (1, 2, 3, 4)}
        clear5 = at(-dirs[5] * a)
        return r_env, a, c, at, corner, clear5, clear5[k]

    geo = {j: geometry(j) for j in order}
    # Repeats revisit the same pose from the same place: reuse the decision.
    memo: dict = prog.__dict__.setdefault("_decisions", {})

    def memo_key(j: int, here: np.ndarray) -> tuple:
        return (ip, j, tuple(np.round(here, 9)) if not np.any(np.isnan(here)) else None)

    def candidates(j: int, here: np.ndarray) -> tuple:
        """The moves whose clearance decides ball j's visit from ``here``: (segments, ball
        each may touch or -1, groups, z_in)."""
        r_env, a, _, at, corner, clear5, z_pole = geo[j]
        known = not np.any(np.isnan(here))
        z_in = {tt: higher(transit(here[hz] if known else corner[tt][hz], corner[tt][hz]),
                           corner[tt][k], z_pole) for tt in (1, 2, 3, 4)}
        # Visiting order of the equator touches: the cheapest rotation/direction around the
        # square whose moves stay clear; an edge blocked by a neighbour is lifted over it.
        up_pole = {tt: [(corner[tt], with_z(corner[tt], z_pole)),
                        (with_z(corner[tt], z_pole), clear5)] for tt in (1, 2, 3, 4)}
        down = {tt: [(with_z(corner[tt], z_in[tt]), corner[tt])] for tt in (1, 2, 3, 4)}
        # up at ``here`` and across to the corner: a transit the heights model got wrong (a
        # steep table) is lifted to z_safe below; checked in the same batch
        over = {tt: way_over(here, corner[tt], z_in[tt]) if known else []
                for tt in (1, 2, 3, 4)}
        groups = ([down[tt] for tt in (1, 2, 3, 4)] + [up_pole[tt] for tt in (1, 2, 3, 4)]
                  + [[(corner[ta], corner[tb])] for ta, tb in _SIDES]
                  + [over[tt] for tt in (1, 2, 3, 4)])
        # Radial moves (corner ⇄ probing line) are rapids when both dog-legs are clear of the
        # other balls, else linear moves at the machine's max feed: checked in the same batch.
        ends = {tt: at(-dirs[tt] * (r_env - prog.overtravel_mm)) for tt in (1, 2, 3, 4)}
        clears = {tt: at(-dirs[tt] * a) for tt in (1, 2, 3, 4)}
        radial = [(corner[tt], clears[tt]) for tt in (1, 2, 3, 4)] + \
            [(ends[tt], corner[tt]) for tt in (1, 2, 3, 4)]
        flat = [seg for g in groups for seg in g]
        return flat + radial, [-1] * len(flat) + [j] * len(radial), (groups, up_pole, down), z_in

    def decide(j: int, here: np.ndarray, cand: tuple, sl: np.ndarray) -> tuple:
        """Ball j's visit from ``here`` given the slack ``sl`` of its ``candidates``."""
        _, _, _, _, corner, _, z_pole = geo[j]
        known = not np.any(np.isnan(here))
        _, _, (groups, up_pole, down), z_in = cand
        ok, i0 = [], 0
        for g in groups:
            ok.append(bool(sl[i0:i0 + len(g)].min(initial=np.inf) >= 0))
            i0 += len(g)
        fmax = prog.machine_file.dynamics.max_feed_mm_min
        f_in = {tt: 0.0 if sl[i0 + tt - 1] >= 0 else fmax for tt in (1, 2, 3, 4)}
        f_out = {tt: 0.0 if sl[i0 + tt + 3] >= 0 else fmax for tt in (1, 2, 3, 4)}
        down_ok = dict(zip((1, 2, 3, 4), ok[:4], strict=True))
        up_ok = dict(zip((1, 2, 3, 4), ok[4:8], strict=True))
        over_ok = dict(zip((1, 2, 3, 4), ok[12:16], strict=True))
        edges: dict[tuple[int, int], list] = {}
        edge_ok: dict[tuple[int, int], bool] = {}
        for (ta, tb), good in zip(_SIDES, ok[8:12], strict=True):
            path, good_path = [(corner[ta], corner[tb])], good
            if not good:
                for z in (z_pole, higher(transit(corner[ta][hz], corner[tb][hz]), z_pole)):
                    u, o = with_z(corner[ta], z), with_z(corner[tb], z)
                    path = [(corner[ta], u), (u, o), (o, corner[tb])]
                    if slack(path).min() >= 0:
                        good_path = True
                        break
            edges[(ta, tb)], edge_ok[(ta, tb)] = path, good_path
            edges[(tb, ta)] = [(p1, p0) for p0, p1 in reversed(path)]
            edge_ok[(tb, ta)] = good_path

        best = None
        lengths: dict[int, float] = {}  # per segment: the 8 orders share them
        for first in (1, 2, 3, 4):
            for step in (1, -1):
                visit = [(first - 1 + step * i) % 4 + 1 for i in range(4)]
                path = down[visit[0]] + [seg for ta, tb in itertools.pairwise(visit)
                                         for seg in edges[(ta, tb)]] + up_pole[visit[-1]]
                good = (down_ok[visit[0]] and up_ok[visit[-1]]
                        and all(edge_ok[e] for e in itertools.pairwise(visit)))
                cost = sum(seg_length(seg, lengths) for seg in path)
                cost += float(np.linalg.norm(here - path[0][0])) if known else 0.0
                # rounded: ties break by order, not noise
                rank = (not good, not over_ok[visit[0]], round(cost, 6))
                if best is None or rank < best[0]:
                    best = (rank, visit)
        visit = best[1]
        if not over_ok[visit[0]]:  # a steep table the heights model got wrong
            z_in = {**z_in, visit[0]: higher(z_in[visit[0]], z_safe())}
        return visit, edges, f_in, f_out, z_in

    # Where the tool stands before each ball is known in advance (the pole touch, always last,
    # retracts to the pole's clearance height above its end point): the clearance of every
    # ball's candidate moves is computed in one batch. A start that turns out different when
    # the moves are emitted is decided again from where the tool really is.
    planned: dict[int, tuple] = {}
    here = np.array(bld.pos[:3])
    for j in order:
        if memo_key(j, here) not in memo:
            planned[j] = (here, candidates(j, here))
        r_env, _, _, at, _, _, z_pole = geo[j]
        here = np.array([float(x) for x in at(-dirs[5] * (r_env - prog.overtravel_mm))])
        here[k] = float(z_pole)
    if planned:
        segs = [s for _, cand in planned.values() for s in cand[0]]
        owns = [o for _, cand in planned.values() for o in cand[1]]
        sl_all, i0 = slack(segs, owns), 0
        for j, (h, cand) in planned.items():
            n = len(cand[0])
            planned[j] = (h, cand, sl_all[i0:i0 + n])
            i0 += n

    for j in order:
        ball = artefact.balls[j]
        r_env, a, c, at, corner, _, z_pole = geo[j]
        here = np.array(bld.pos[:3])
        known = not np.any(np.isnan(here))  # unknown right after the program start
        key = memo_key(j, here)
        if key in memo:
            visit, edges, f_in, f_out, z_in = memo[key]
        else:
            if j in planned and np.array_equal(planned[j][0], here, equal_nan=True):
                _, cand, sl = planned[j]
            else:
                cand = candidates(j, here)
                sl = slack(cand[0], cand[1])
            visit, edges, f_in, f_out, z_in = memo[key] = decide(j, here, cand, sl)

        kw0 = {"pose": ip, "ball": ball.id}
        first = corner[visit[0]]
        z = z_in[visit[0]]
        if known:  # else stay at the start retract (the end of travel) for the first move
            bld.emit("rapid", axes_only({k: z}), **kw0)
        bld.emit("rapid", axes_only({i: first[i] for i in hz}), **kw0)
        bld.emit("rapid", axes_only({k: first[k]}), **kw0)
        for tt in [*visit, 5]:
            seq += 1
            d = dirs[tt]
            start = at(-d * (r_env + prog.standoff_mm))
            clear = at(-d * a)
            contact = at(-d * r_env)
            end = at(-d * (r_env - prog.overtravel_mm))
            touch = Touch(TouchId(seq, ip, ball.id, tt, rep), j + 1, t3(d),
                          pose.b_deg, pose.c_deg, t3(c), t3(start), t3(contact),
                          t3(end), plan.feeds.probe_mm_min)
            prog.touches.append(touch)
            kw = {**kw0, "touch": touch}
            if tt < 5:
                prev = np.array(bld.pos[:3])
                if np.linalg.norm(prev - corner[tt]) > 1e-9:
                    ta = next(x for x in visit if np.linalg.norm(prev - corner[x]) < 1e-9)
                    for _, p1 in edges[(ta, tt)]:
                        bld.emit("rapid", [*p1, None, None], **kw)  # around the square
                bld.emit("feed" if f_in[tt] else "rapid", [*clear, None, None],
                         feed_mm_min=f_in[tt], **kw)  # in along the probing line
            else:
                bld.emit("rapid", axes_only({k: z_pole}), **kw)  # up beside the ball
                bld.emit("rapid", [*clear, None, None], **kw)  # across over the pole
            if plan.dwell_s > 0:
                bld.emit("dwell", [None] * 5, dwell_s=plan.dwell_s, **kw)
            bld.emit("feed", [*start, None, None], feed_mm_min=plan.feeds.approach_mm_min, **kw)
            bld.emit("probe", [*end, None, None], feed_mm_min=plan.feeds.probe_mm_min,
                     locate_feed_mm_min=fast or 0.0, backoff_mm=BACKOFF_MM if fast else 0.0,
                     **kw)
            if tt < 5:
                bld.emit("retract", [*corner[tt], None, None], feed_mm_min=f_out[tt],
                         **kw)
            else:  # only out of the ball: the next transit rises as far as it must
                bld.emit("retract", axes_only({k: z_pole}), **kw)
    return seq

