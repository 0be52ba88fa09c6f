"""A ball that moved during the run: knocked or loose in its holder, a step.

Thesis §3.3: the method needs the artefact stable during a session. A step of ball b between
visit k and k+1 adds to every later centre of b the ball-setup Jacobian times the step vector
(three parameters, last workpiece frame); the setup estimate takes the position before the
step. The scan fits every (ball, moment) on the current whitening (per visit when the scatter
is modelled) and keeps the best one when

* its nested F-test against the twin (3 dof) is significant at ``ALPHA`` after Bonferroni over
  every (ball, moment) tried (the scan's own look-elsewhere cost), and
* it fits better than every library effect alone (the ``rivals``: a drift, a straightness, a
  sag, the same ball creeping at a constant velocity …), each penalised by its parameters
  (BIC, k ln n) and the step also by the scan's selection, 2 ln(moments tried): a systematic
  residual of the twin leans on one ball's later visits too, and a creep would otherwise be
  named a step at its middle.

The step is then part of the twin (setup, links and the rest are fitted with it), and the
report names the ball, the two visits it fell between, its vector and size with uncertainty.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from identification.gap.attribute import ALPHA, f_test
from identification.gap.data import Groups
from identification.gap.linear import Problem, fit

MIN_SIDE = 2  # visits of the ball on each side of the step: one visit alone is an outlier


@dataclass
class Step:
    ball: int
    after_visit: int  # index in time order of the last visit before the step
    cols: np.ndarray  # (G, 4, 3) µm per µm of step (last workpiece frame)
    p_value: float
    before: tuple[int, int, float]  # (repeat, pose, time s) of the last visit before
    after: tuple[int, int, float]  # (repeat, pose, time s) of the first visit after
    rival_bic: float
    step_bic: float


def _visit_order(groups: Groups) -> tuple[np.ndarray, list[int]]:
    c = groups.centres
    key = groups.repeat.astype(np.int64) * 1_000_000 + c.pose
    start = {int(k): float(c.t_s[key == k].min()) for k in np.unique(key)}
    return key, sorted(start, key=start.get)


def find_step(problem: Problem, groups: Groups, ball_jac: np.ndarray,
              rivals: Sequence[np.ndarray] = ()) -> Step | None:
    """The most significant single-ball step, or None (see the module docstring);
    ``rivals``: the library effects' columns (G, 4, m)."""
    key, order = _visit_order(groups)
    rank = {k: i for i, k in enumerate(order)}
    vrank = np.array([rank[int(k)] for k in key])
    base_full = fit(problem, problem.base)
    tried, best = 0, None
    for b in np.unique(groups.centres.ball):
        mine = groups.centres.ball == b
        ranks = np.unique(vrank[mine])
        jac = np.zeros((len(groups), 4, 3))
        jac[mine, :3, :] = ball_jac[mine]
        for k in ranks[MIN_SIDE - 1:len(ranks) - MIN_SIDE]:
            tried += 1
            cols = jac * (vrank > k)[:, None, None]
            full = fit(problem, np.concatenate([problem.base, cols], axis=2))
            if best is None or full.rss_w < best[0].rss_w:
                best = (full, int(b), int(k), cols)
    if best is None:
        return None
    full, b, k, cols = best
    p, _ = f_test(base_full, full)
    if p * tried >= ALPHA:
        return None

    def bic(f) -> float:
        return f.rss_w + (f.rank - base_full.rank) * np.log(f.n_obs)

    step_bic = bic(full) + 2.0 * np.log(max(tried, 2))
    rival = min((bic(fit(problem, np.concatenate([problem.base, r], axis=2))) for r in rivals),
                default=np.inf)
    if step_bic >= rival:
        return None
    c = groups.centres

    def visit(r: int) -> tuple[int, int, float]:
        g = np.flatnonzero(vrank == r)[0]
        return int(groups.repeat[g]), int(c.pose[g]), float(c.t_s[vrank == r].min())

    return Step(b, k, cols, float(min(p * tried, 1.0)), visit(k), visit(k + 1), float(rival),
                float(step_bic))


def step_report(step: Step, problem: Problem, ids: list[str], n_before: int) -> dict:
    """The report's ``ball_step`` part: ball, between which visits, vector and size ± u (µm),
    from the twin's fit with the step (its columns at ``n_before`` of the base)."""
    full = fit(problem, problem.base)
    v = full.beta[n_before:n_before + 3]
    cov = full.cov[n_before:n_before + 3, n_before:n_before + 3]
    size = float(np.linalg.norm(v))
    u = float(np.sqrt(max(v @ cov @ v, 0.0)) / size) if size > 0 else float("nan")
    (r0, p0, t0), (r1, p1, t1) = step.before, step.after
    rep = lambda r: f" repeat {r}" if r else ""  # noqa: E731
    where = f"between pose {p0}{rep(r0)} ({t0 / 60:.1f} min) and pose {p1}{rep(r1)} " \
            f"({t1 / 60:.1f} min)"
    return {"ball": ids[step.ball], "after_pose": p0, "after_repeat": r0, "before_pose": p1,
            "before_repeat": r1, "t_after_s": round(t0, 1), "t_before_s": round(t1, 1),
            "vector_um": [round(float(x), 3) for x in v],
            "vector_std_um": [round(float(np.sqrt(max(cov[i, i], 0.0))), 3) for i in range(3)],
            "size_um": round(size, 3), "size_std_um": round(u, 3),
            "p_value": float(f"{step.p_value:.3g}"),
            "message": (f"ball {ids[step.ball]} moved by {size:.1f} ± {u:.1f} µm "
                        f"({', '.join(f'{x:+.1f}' for x in v)} µm x/y/z, workpiece frame) "
                        f"{where}: knocked or loose in its holder; the links are those with "
                        f"the step modelled")}


def step_verdict(rep: dict) -> dict:
    """With a step the verdict is ``ball_moved`` naming it; what the diagnosis reads with the
    step modelled is kept under ``verdict.with_step_modelled``."""
    step = rep.get("ball_step")
    if not step:
        return rep
    v = rep["verdict"]
    axis = f":{v['axis']}" if v["axis"] else ""
    rep["verdict"] = {**v, "effect": "ball_moved", "axis": None,
                      "with_step_modelled": {"effect": v["effect"], "axis": v["axis"],
                                             "message": v["message"]},
                      "message": (f"{step['message']}; with the step modelled the rest reads "
                                  f"{v['effect']}{axis} ({v['message']})")}
    return rep
