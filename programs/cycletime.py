"""Cycle-time estimate of a probing program and a lower bound for the same plan.

Estimate: every move at its programmed speed, no acceleration (rapids at
``dynamics.rapid_mm_min`` along the straight line, feeds at F, probing moves stop at the
expected contact — a two-speed one after its fast approach, the back-off at the approach feed
and the slow re-touch over the back-off —, each rotary index at ``rotary_rapid_deg_min`` for
the larger of the two rotary moves plus ``rotary_clamp_s``, dwells). Lower bound for the same
plan and machine: the probing of every touch as the estimate counts it, plus a minimum spanning
tree of each pose's touch start points at rapid (no tour through them can be shorter), plus the
index moves the plan's pose order imposes and the dwells. The first move from the unknown
position at program start is not counted in either.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from programs.model import Move, Program, plan_visits


@dataclass(frozen=True)
class CycleTime:
    estimate_s: float
    lower_bound_s: float
    parts_s: dict[str, float] = field(default_factory=dict)  # rapid, linear, probe, index, dwell

    @property
    def ratio(self) -> float:
        return self.estimate_s / self.lower_bound_s if self.lower_bound_s > 0 else math.inf

    def summary(self) -> str:
        return (f"estimated {_mmss(self.estimate_s)} (lower bound {_mmss(self.lower_bound_s)}, "
                f"ratio {self.ratio:.2f})")


def _mmss(s: float) -> str:
    m, sec = divmod(round(s), 60)
    return f"{m} min {sec:02d} s"


def _index_s(prog: Program, a: np.ndarray, b: np.ndarray) -> float:
    dyn = prog.machine_file.dynamics
    delta = float(np.max(np.abs(b - a)))
    if delta <= 1e-12:
        return 0.0
    return delta / dyn.rotary_rapid_deg_min * 60.0 + dyn.rotary_clamp_s


def estimate(prog: Program, linear_rapid: bool = False) -> CycleTime:
    """Estimate and lower bound (seconds) of a generated program; ``linear_rapid``: the
    dialect renders the checked straight transits (``Move.linear_rapid``) as rapids."""
    dyn = prog.machine_file.dynamics
    parts = {"rapid": 0.0, "linear": 0.0, "probe": 0.0, "index": 0.0, "dwell": 0.0}
    pos = np.full(5, np.nan)
    for mv in prog.moves:
        tgt = np.array(mv.target, float)
        if mv.kind == "dwell":
            parts["dwell"] += mv.dwell_s
            continue
        known = not np.any(np.isnan(pos))
        if mv.kind == "probe" and mv.touch is not None:
            parts["probe"] += probe_s(mv, prog.plan.feeds.approach_mm_min)
            pos = tgt.copy()
            pos[:3] = mv.touch.contact  # the probe stops at the contact
            continue
        if known:
            if np.any(np.abs(tgt[3:] - pos[3:]) > 1e-12):
                parts["index"] += _index_s(prog, pos[3:], tgt[3:])
            dist = float(np.linalg.norm(tgt[:3] - pos[:3]))
            if mv.feed_mm_min > 0 and not (linear_rapid and mv.linear_rapid):
                parts["linear"] += dist / mv.feed_mm_min * 60.0
            else:
                parts["rapid"] += dist / dyn.rapid_mm_min * 60.0
        pos = tgt
    return CycleTime(sum(parts.values()), lower_bound(prog), parts)


def lower_bound(prog: Program) -> float:
    """Probing at probe feed + MST of each pose's start points at rapid + indexes + dwells."""
    dyn, plan = prog.machine_file.dynamics, prog.plan
    probing_s = sum(probe_s(mv, plan.feeds.approach_mm_min) for mv in prog.moves
                    if mv.kind == "probe" and mv.touch is not None)
    groups: dict[tuple[int, int], list] = {}
    for t in prog.touches:
        groups.setdefault((t.id.repeat, t.id.pose), []).append(t.start)
    tour_mm = 0.0
    for pts in groups.values():
        p = np.array(pts)
        if len(p) > 1:
            tour_mm += mst_length_mm(p)
    rot = [np.array([plan.poses[ip].b_deg, plan.poses[ip].c_deg]) for _, ip in plan_visits(plan)]
    index_s = sum(_index_s(prog, a, b) for a, b in itertools.pairwise(rot))
    dwell_s = plan.dwell_s * len(prog.touches)
    return probing_s + tour_mm / dyn.rapid_mm_min * 60.0 + index_s + dwell_s


def mst_length_mm(p: np.ndarray) -> float:
    """Length of a minimum spanning tree of the points ``p`` (N, 3) under straight distances:
    Prim's algorithm on the dense distance matrix (N is a pose's touches, a few dozen), the
    edges summed in the order (i < j, row-major) scipy's ``minimum_spanning_tree(cdist).sum()``
    sums them, so the total is the same to the last bit, without scipy's import."""
    d = np.sqrt(((p[:, None, :] - p[None, :, :]) ** 2).sum(axis=2))
    n = len(p)
    inside = np.zeros(n, bool)
    inside[0] = True
    best, parent = d[0].copy(), np.zeros(n, int)
    edges = []
    for _ in range(n - 1):
        j = int(np.argmin(np.where(inside, np.inf, best)))
        edges.append((min(parent[j], j), max(parent[j], j), best[j]))
        inside[j] = True
        closer = d[j] < best
        parent[closer] = j
        best = np.where(closer, d[j], best)
    return float(np.sum([w for _, _, w in sorted(edges)])) if edges else 0.0


def probe_s(mv: Move, approach_mm_min: float) -> float:
    """Seconds of one probing move up to the expected contact: at its feed, or for a two-speed
    touch the fast approach, the back-off at the approach feed and the slow re-touch."""
    assert mv.touch is not None
    dist = float(np.linalg.norm(np.array(mv.touch.contact) - np.array(mv.touch.start)))
    if mv.locate_feed_mm_min <= 0:
        return dist / mv.feed_mm_min * 60.0
    return (dist / mv.locate_feed_mm_min + mv.backoff_mm / approach_mm_min
            + mv.backoff_mm / mv.feed_mm_min) * 60.0
