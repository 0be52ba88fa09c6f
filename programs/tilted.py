"""Tool path for a tilted probe: poses at which the spindle is not along one controller
linear axis (swivel and fork heads), through the linear axes only — no TCPM (METHOD.md §1
geometry, in the tool frame).

At a fixed rotary pose the relative position r = tip − ball centre (foundation frame) is affine
in the controller X Y Z (``programs.geometry.PoseFrame``), so a straight controller move is a
straight stylus move and ``q = q_centre + J⁻¹ r`` is exact. The touches are those of
``programs.toolpath`` carried into the tool frame (``contracts.touch_frame``): the pole
against the spindle direction s at that pose, the four equator directions the machine X-Y
diagonals turned by the smallest rotation taking z onto s (identical to today's where s = z),
all four turned about s by the first of ``EQUATOR_TURNS_DEG`` whose path is clear of the rods.

The path: before every index the park axis (the controller axis most along the spindle at the
rotary home, Z on a vertical head) goes to its travel end, the rotary axes index there; the tip
crosses at the park value and comes down the park axis to the pose's safe level — the level
along s above every ball, rod, the table rim and every box plus stylus radius and the plan's
clearance, so everything of the tool (tip, stem, bodies) is above every keep-out there; the park
axis has a positive component along s, so the way down stays above that level — then descends
along s beside the first ball to its equator, goes round the square and probes as
``programs.toolpath`` does, probes the pole, rises along s to the safe level, crosses to the next
ball at that level (a move in the plane ⊥ s) and goes up the park axis at the end of the pose.
Moves of more than one axis that are not at the park value are linear moves at the machine's
max feed: a non-linear rapid would leave the straight line these moves were checked on. Each
ball's moves are checked at build time (``programs.clearance``, ``programs.bodies``) and a ball
no turn clears is a ``ProgramError`` naming pose, ball and reason; ``programs.safety`` checks
the whole program again, as for every program.
"""

from __future__ import annotations

import math

import numpy as np

from contracts.messages import TouchId
from contracts.touch_frame import EQUATOR_TURNS_DEG, equator_directions
from identification.kinematics import ChainState, Machine
from programs.bodies import body_slack
from programs.clearance import keepout_slack, tip_in_workpiece
from programs.geometry import PoseFrame, ProgramError, pose_frame
from programs.model import Move, Program, Touch, ball_positions, chain_state, plan_visits
from programs.tour import open_tour

APPROACH_GAP_MM = 0.5  # as programs.toolpath: fed at approach feed to the start point
PARK_MIN_RATE = 0.2  # the park axis must move the tip at least this much along the spindle


def head_tilts(machine: Machine) -> bool:
    """Does a rotary axis of the tool chain turn the spindle (swivel or fork head)?"""
    s = np.asarray(machine.spindle_axis, float)
    return any(np.linalg.norm(np.cross(machine.axes[a].direction, s)) > 1e-9
               for a in machine.tool_chain if a in machine.rotary_axes)


def park_value(machine: Machine) -> tuple[int, float]:
    """(axis index, value) the tilted path indexes at: the end of travel of the controller axis
    most along the spindle at the rotary home, on the side away from the work."""
    home = pose_frame(machine, dict.fromkeys(machine.rotary_axes, 0.0), ChainState())
    v0 = home.jinv @ home.spindle
    k = int(np.argmax(np.abs(v0)))
    lo, hi = machine.axes["XYZ"[k]].travel
    return k, (hi if v0[k] > 0 else lo)


def spindle_is_tilted(machine: Machine, pf: PoseFrame) -> bool:
    """Is the spindle at this pose off every controller linear axis?"""
    v = pf.jinv @ pf.spindle
    k = int(np.argmax(np.abs(v)))
    return bool(np.max(np.abs(np.delete(v, k))) > 1e-9 * abs(v[k]))


class _Path:
    """Moves of one program, appended with the words each changes."""

    def __init__(self, prog: Program) -> None:
        self.p = prog
        self.pos = [math.nan] * 5
        self.block = 0
        self.park: tuple[int, float] | None = None  # (axis, value): rapids across up there

    def emit(self, kind: str, target: list[float | None], **kw: object) -> None:
        new = [self.pos[i] if v is None else float(v) for i, v in enumerate(target)]
        letters = self.p.axis_letters
        words = tuple(letters[i] for i in range(5) if target[i] is not None and (
            kind in ("probe", "feed") or not abs(new[i] - self.pos[i]) <= 1e-12))
        if not words:
            return
        self.block += 1
        self.pos = new
        self.p.moves.append(Move(self.block, kind, tuple(new), words, **kw))  # type: ignore[arg-type]

    def go(self, q: np.ndarray, fmax: float, **kw: object) -> None:
        """To controller X Y Z ``q``: a rapid when one axis moves (or two at the park value),
        else a linear move at the max feed that a dialect with straight-line rapids renders as
        a rapid (``Move.linear_rapid``: its straight path is the one checked)."""
        here = np.array(self.pos[:3])
        changed = [i for i in range(3) if not abs(q[i] - here[i]) <= 1e-9]
        if not changed:
            return
        at_park = len(changed) == 2 and self.park is not None and \
            self.park[0] not in changed and abs(here[self.park[0]] - self.park[1]) <= 1e-9
        if len(changed) == 1 or at_park or np.isnan(here).any():
            self.emit("rapid", [*(q[i] if i in changed else None for i in range(3)), None, None],
                      **kw)
        else:
            self.emit("feed", [*q, None, None], feed_mm_min=fmax, linear_rapid=True, **kw)


def build_tilted(prog: Program, frames_: list[PoseFrame], two_speed_feed: float | None,
                 backoff_mm: float) -> Program:
    """Fill ``prog`` (as ``programs.toolpath.build_program`` prepared it) with the tilted-probe
    path of every visit of its plan."""
    machine, mf, art, plan = prog.machine, prog.machine_file, prog.artefact, prog.plan
    state = chain_state(prog.targets)
    balls_w = ball_positions(art, prog.targets)
    rs = plan.stylus_radius_mm
    clr = max(plan.clearance_mm, prog.standoff_mm)
    fmax = mf.dynamics.max_feed_mm_min
    k, park = park_value(machine)
    prog.retract_axis = k
    prog.tilted = True
    path = _Path(prog)
    path.park = (k, park)
    path.emit("rapid", [park if i == k else None for i in range(3)] + [None, None], pose=0)
    prev_rot = None
    seq = 0
    for rep, ip in plan_visits(plan):
        pose, pf = plan.poses[ip], frames_[ip]
        rot = (pose.b_deg, pose.c_deg)
        if rot != prev_rot:  # every pose visit ends at the park value (``_pose``)
            path.emit("rapid", [None, None, None, *rot], pose=ip)
            prev_rot = rot
        seq = _pose(prog, path, pf, ip, rep, seq, balls_w, state, k, park, rs, clr, fmax,
                    two_speed_feed, backoff_mm)
    return prog


def _safe_level(prog: Program, balls_w: np.ndarray, u_w: np.ndarray, rs: float,
                clr: float) -> float:
    """Tip level along the spindle (workpiece frame) above every keep-out + stylus + clearance."""
    art, t = prog.artefact, prog.machine_file.table
    tops = []
    for b, c in zip(art.balls, balls_w, strict=True):
        foot = c - np.array([0.0, 0.0, b.rod_length_mm])
        tops += [u_w @ c + b.diameter_mm / 2, max(u_w @ c, u_w @ foot) + b.rod_diameter_mm / 2]
    tops.append(t.surface_z_mm * u_w[2] + t.radius_mm * math.sqrt(max(0.0, 1 - u_w[2] ** 2))
                + t.clearance_mm)
    for box in prog.machine_file.keep_out:
        corners = np.array(np.meshgrid(*zip(box.min_mm, box.max_mm, strict=True))).T.reshape(-1, 3)
        tops.append(float((corners @ u_w).max()) + t.clearance_mm)
    return max(tops) + rs + clr


def _pose(prog: Program, path: _Path, pf: PoseFrame, ip: int, rep: int, seq: int,
          balls_w: np.ndarray, state: ChainState, k: int, park: float, rs: float, clr: float,
          fmax: float, fast: float | None, backoff_mm: float) -> int:
    machine, art, plan = prog.machine, prog.artefact, prog.plan
    s = pf.spindle
    u_w = pf.r_fw.T @ s
    v = pf.jinv @ s  # controller motion per mm along the spindle
    if abs(v[k]) < PARK_MIN_RATE:
        raise ProgramError(f"pose {ip}: the spindle {np.round(s, 4).tolist()} is almost "
                           f"perpendicular to the park axis {'XYZ'[k]}: cannot leave along it")
    level = _safe_level(prog, balls_w, u_w, rs, clr)
    centres = pf.solve(machine, balls_w, state)
    hz = [i for i in range(3) if i != k]
    here = np.array(path.pos[:3])
    order = open_tour(centres[:, hz], here[hz] if not np.isnan(here).any()
                      else np.full(2, np.nan))
    pose = plan.poses[ip]
    for n_ball, j in enumerate(order):
        ball = art.balls[j]
        c = centres[j]
        r_env = ball.diameter_mm / 2 + rs
        a = r_env + prog.standoff_mm + APPROACH_GAP_MM
        h = level - float(u_w @ balls_w[j])  # rise from the ball's equator to the safe level
        reason, choice = "", None
        for turn in EQUATOR_TURNS_DEG:
            dirs = equator_directions(s, turn)
            segs = _ball_segments(c, pf, dirs, a, r_env, prog.overtravel_mm, h)
            q = np.array([p for seg in segs for p in seg])
            full = np.column_stack([q, np.broadcast_to([pose.b_deg, pose.c_deg], (len(q), 2))])
            pw = tip_in_workpiece(prog, full)
            pa, pb = pw[0::2], pw[1::2]
            own = np.full(len(pa), -1)  # the probing lines may enter ball j's envelope
            own[_RADIAL] = j
            stem = np.broadcast_to(u_w, pa.shape)
            sl, why = keepout_slack(prog, pa, pb, own, stem)
            bl, bwhy = body_slack(prog, pa, pb, stem)
            if sl.min() >= 0 and bl.min() >= 0:
                choice = dirs
                break
            reason = why(int(np.argmin(sl))) if sl.min() < 0 else bwhy(int(np.argmin(bl)))
        if choice is None:
            raise ProgramError(f"pose {ip} ({prog.rotary[0]}{pose.b_deg:g} "
                               f"{prog.rotary[1]}{pose.c_deg:g}), ball {ball.id}: no clear "
                               f"tilted-probe path ({reason})")
        dirs = choice

        def at(r: np.ndarray, _c: np.ndarray = c) -> np.ndarray:
            return _c + pf.jinv @ r

        kw0 = {"pose": ip, "ball": ball.id}
        first = at(-dirs[1] * a * math.sqrt(2))
        entry = first + h * v
        if n_ball == 0:  # from the park value: across up there, then down the park axis
            path.go(np.array([park if i == k else entry[i] for i in range(3)]), fmax, **kw0)
        path.go(entry, fmax, **kw0)
        path.go(first, fmax, **kw0)
        for tt in (1, 2, 3, 4, 5):
            seq += 1
            d = dirs[tt]
            start, contact = at(-d * (r_env + prog.standoff_mm)), at(-d * r_env)
            end, clear = at(-d * (r_env - prog.overtravel_mm)), at(-d * a)
            touch = Touch(TouchId(seq, ip, ball.id, tt, rep), j + 1, _t3(d), pose.b_deg,
                          pose.c_deg, _t3(c), _t3(start), _t3(contact), _t3(end),
                          plan.feeds.probe_mm_min)
            prog.touches.append(touch)
            kw = {**kw0, "touch": touch}
            corner = at(-d * a * math.sqrt(2)) if tt < 5 else None
            if tt < 5:
                path.go(corner, fmax, **kw)
            else:
                path.go(path_pos(path) + a * v, fmax, **kw)  # up beside the ball
            path.go(clear, fmax, **kw)
            if plan.dwell_s > 0:
                path.emit("dwell", [None] * 5, dwell_s=plan.dwell_s, **kw)
            path.emit("feed", [*start, None, None], feed_mm_min=plan.feeds.approach_mm_min, **kw)
            path.emit("probe", [*end, None, None], feed_mm_min=plan.feeds.probe_mm_min,
                      locate_feed_mm_min=fast or 0.0, backoff_mm=backoff_mm if fast else 0.0,
                      **kw)
            path.emit("retract", [*(corner if tt < 5 else clear), None, None],
                      feed_mm_min=fmax, linear_rapid=True, **kw)  # checked straight: _RADIAL
        path.go(at(h * s), fmax, **kw0)  # up along the spindle to the safe level; the next
        # ball's entry is at the same level: across in the plane ⊥ s, above every keep-out
    here = path_pos(path)  # up the park axis: every point above the safe level stays above it
    path.go(np.array([park if i == k else here[i] for i in range(3)]), fmax, pose=ip)
    return seq


def path_pos(path: _Path) -> np.ndarray:
    """Where the path's X Y Z stand now."""
    return np.array(path.pos[:3], float)


# Which of ``_ball_segments`` are probing lines (in to the overtravel end and back out).
_RADIAL = [1, 2, 4, 5, 7, 8, 10, 11, 14, 15]


def _ball_segments(c: np.ndarray, pf: PoseFrame, dirs: dict[int, np.ndarray], a: float,
                   r_env: float, overtravel: float, h: float) -> list[tuple[np.ndarray, ...]]:
    """Controller segments of one ball's moves (for the build-time check): down along the
    spindle to the first corner, round the square with the radial moves in and out, up, over
    the pole, probe it, back up to the safe level."""
    def at(r: np.ndarray) -> np.ndarray:
        return c + pf.jinv @ r

    s = pf.spindle
    corner = {tt: at(-dirs[tt] * a * math.sqrt(2)) for tt in (1, 2, 3, 4)}
    segs = [(corner[1] + pf.jinv @ (h * s), corner[1])]
    for tt in (1, 2, 3, 4):
        if tt > 1:
            segs.append((corner[tt - 1], corner[tt]))
        end = at(-dirs[tt] * (r_env - overtravel))
        segs += [(corner[tt], end), (end, corner[tt])]
    up = corner[4] + pf.jinv @ (a * s)
    top, pole_end = at(a * s), at(s * (r_env - overtravel))
    segs += [(corner[4], up), (up, top), (top, pole_end), (pole_end, top), (top, at(h * s))]
    return segs


def _t3(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))
