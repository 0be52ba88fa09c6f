"""Clearance of stylus moves: the tip in the workpiece frame and the slack of tip segments (and
the stem they sweep) against every keep-out — shared by the tool path and the safety check."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from programs.geometry import tip_affine
from programs.model import Program, ball_positions

TOL_MM = 1e-6
BOUND_MM = 1e-6  # a bound is trusted to this (its rounding: ~1e-13 of a few hundred mm)


def tip_in_workpiece(prog: Program, q: np.ndarray) -> np.ndarray:
    """Stylus-tip centre in the last workpiece frame for controller states q (N, 5).

    For fixed rotary joints the chain is affine in the linear axes (no motion errors here), so
    each distinct rotary state costs four chain evaluations and every point one product."""
    a, b, inv = _affine(prog, q[:, 3:5])
    return b[inv] + np.einsum("ni,nij->nj", q[:, :3], a[inv])


def _affine(prog: Program, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    bits = np.ascontiguousarray(rot, float).view(np.int64)
    if len(rot) and (bits == bits[0]).all():  # one rotary state, bit for bit: no sort
        uniq, inv = rot[:1], np.zeros(len(rot), int)
    else:
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


def keepout_slack(prog: Program, pa: np.ndarray, pb: np.ndarray, own: np.ndarray,
                  stem: np.ndarray | None = None, free_sphere: np.ndarray | None = None
                  ) -> tuple[np.ndarray, Callable[[int], str]]:
    """Slack (mm, < 0 = violation) of tip segments pa→pb (workpiece frame) against every keep-out,
    and a function giving the reason for segment j's tightest one. ``own`` is the ball index a
    probing or retract segment may touch (its sphere is exempt, its rod has no standoff margin),
    or -1. ``stem`` (N, 3): unit spindle direction in the workpiece frame; the stylus stem (a
    cylinder of ``plan.stylus_length_mm`` from the tip) then sweeps a parallelogram per segment
    that must keep the standoff from every ball and rod (own ball and rod exempt on probing
    lines). All balls are handled in one vectorised pass (segments × balls). ``free_sphere``
    (N,): a ball index per segment whose sphere is left out as well (the ball a move works on:
    its approach ends on that sphere's standoff by construction) — for a reported margin, never
    for the check."""
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
    free = is_own if free_sphere is None else is_own | (
        np.tile(free_sphere, nb) == np.repeat(np.arange(nb), n)).reshape(nb, n)
    kinds: list[tuple[str, np.ndarray]] = []  # (reason template, gap (nb, n))
    slacks: list[np.ndarray] = []

    gap = (seg_point(pa_k, pb_k, c_k).reshape(nb, n) - (r_ball + rs)[:, None])
    slacks.append(np.where(free, np.inf, gap - standoff + TOL_MM))
    kinds.append(("stylus comes {gap:.3f} mm from ball {ball} (keep-out: ball + stylus radius "
                  f"+ standoff {standoff:g} mm)", gap))
    gap = seg_seg(pa_k, pb_k, top_k, bot_k).reshape(nb, n) - (r_rod + rs)[:, None]
    slacks.append(gap - np.where(is_own, 0.0, standoff) + TOL_MM)
    kinds.append(("stylus comes {gap:.3f} mm from the rod of ball {ball}", gap))
    t = mf.table
    table = below_disc(pa, pb, t.surface_z_mm + t.clearance_mm + rs,
                       t.radius_mm + t.clearance_mm + rs)
    boxes = []
    for box in mf.keep_out:
        grow = rs + t.clearance_mm
        lo, hi = np.array(box.min_mm) - grow, np.array(box.max_mm) + grow
        boxes.append(seg_box(pa, pb, lo, hi))
    if stem is not None:
        # The stem's parallelograms against every ball and rod, exactly only where a pair can
        # be a segment's tightest: a pair whose bound (its parallelogram's bounding sphere) is
        # already looser than what the segment has got leaves the minimum and the reason as
        # they are — the same numbers, most of the far pairs never computed.
        got = np.minimum(np.minimum(slacks[0], slacks[1]).min(axis=0, initial=np.inf),
                         np.where(table | np.any(boxes, axis=0), -1.0, np.inf))
        e1, e2 = pb - pa, stem * plan.stylus_length_mm
        mid = pa + 0.5 * e1 + 0.5 * e2
        reach = 0.5 * (np.linalg.norm(e1, axis=1) + np.linalg.norm(e2, axis=1))
        r_st = plan.stem_radius_mm
        near = np.linalg.norm(mid[None] - balls_w[:, None], axis=2) - reach[None]
        bound = np.maximum(near, 0.0) - (r_ball + r_st + standoff)[:, None] + TOL_MM
        gap = np.full((nb, n), np.inf)
        need = np.nonzero((~free & (bound - BOUND_MM <= got[None])).ravel())[0]
        if need.size:
            gap.ravel()[need] = point_par(c_k[need], pa_k[need], tile(e1)[need],
                                          tile(e2)[need]) - np.repeat(r_ball, n)[need] - r_st
        slacks.append(np.where(free, np.inf, gap - standoff + TOL_MM))
        kinds.append(("stylus stem comes {gap:.3f} mm from ball {ball}", gap))
        got = np.minimum(got, slacks[-1].min(axis=0, initial=np.inf))
        half = 0.5 * np.linalg.norm(top - bot, axis=1)
        near = (np.linalg.norm(mid[None] - (0.5 * (top + bot))[:, None], axis=2)
                - reach[None] - half[:, None])
        bound = np.maximum(near, 0.0) - (r_rod + r_st + standoff)[:, None] + TOL_MM
        gap = np.full((nb, n), np.inf)
        need = np.nonzero((~is_own & (bound - BOUND_MM <= got[None])).ravel())[0]
        if need.size:
            gap.ravel()[need] = seg_par(top_k[need], bot_k[need], pa_k[need], tile(e1)[need],
                                        tile(e2)[need]) - np.repeat(r_rod, n)[need] - r_st
        slacks.append(np.where(is_own, np.inf, gap - standoff + TOL_MM))
        kinds.append(("stylus stem comes {gap:.3f} mm from the rod of ball {ball}", gap))
    slacks.append(np.where(table, -1.0, np.inf)[None, :])
    kinds.append((f"stylus enters the table keep-out (surface z {t.surface_z_mm:g} + clearance "
                  f"{t.clearance_mm:g} mm, radius {t.radius_mm:g} mm)", np.zeros((1, n))))
    for box, hit in zip(mf.keep_out, boxes, strict=True):
        slacks.append(np.where(hit, -1.0, np.inf)[None, :])
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


# ------------------------------------------------------------------ vectorised distance helpers


def seg_point(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    ab = b - a
    L2 = np.einsum("ij,ij->i", ab, ab)
    t = np.where(L2 > 0, np.einsum("ij,ij->i", p - a, ab) / np.where(L2 > 0, L2, 1), 0.0)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * ab - p, axis=1)


def _edges(p0: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The four edges of parallelograms p0 + s·e1 + t·e2, stacked (4 N, 3): start, end."""
    p1, p2 = p0 + e1, p0 + e2
    p12 = p0 + e1 + e2
    return np.concatenate([p0, p2, p0, p1]), np.concatenate([p1, p12, p2, p12])


def point_par(c: np.ndarray, p0: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Distance from points c to parallelograms p0 + s·e1 + t·e2 (s, t in [0, 1])."""
    a, b = _edges(p0, e1, e2)
    d = seg_point(a, b, np.tile(c, (4, 1))).reshape(4, -1).min(axis=0)  # one pass, 4 edges
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


def seg_par(r0: np.ndarray, r1: np.ndarray, p0: np.ndarray, e1: np.ndarray,
             e2: np.ndarray) -> np.ndarray:
    """Distance from segments r0→r1 to parallelograms p0 + s·e1 + t·e2: the closer of the
    segment to the four edges and its end points to the face, 0 where it pierces the face."""
    a, b = _edges(p0, e1, e2)
    n = len(r0)
    edge = seg_seg(np.tile(r0, (4, 1)), np.tile(r1, (4, 1)), a, b).reshape(4, n).min(axis=0)
    ends = point_par(np.concatenate([r0, r1]), *(np.tile(x, (2, 1)) for x in (p0, e1, e2)))
    d = np.minimum(edge, ends.reshape(2, n).min(axis=0))
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


def seg_seg(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
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


def below_disc(pa: np.ndarray, pb: np.ndarray, z_thr: float, radius: float) -> np.ndarray:
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


def seg_box(pa: np.ndarray, pb: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
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
