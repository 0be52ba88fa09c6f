"""Run order of the poses ``rumba plan`` chose: a closed tour from the revisited pose back to it
(the drift check), short rotary moves, and time not sorted along C.

C values are taken modulo 360° so that the largest empty arc between the chosen C angles is
the one never crossed (a 330° pose next to a 0° one is written −30°, within the C travel), so
no index turns C the long way round. The tour minimises the modelled seconds between visits
(``Candidates.transition_s``: index with its clamp cycle, retract, traverse) — exhaustively for
up to eight poses, by 2-opt beyond — among orders whose C values are not monotone: visits
adjacent in C then lie far apart in time, so a linear drift and an effect of C are not
confounded (with the revisit at the end measuring the drift itself: identification/gap).
Among tours within ``TIE_FRACTION`` of the fastest, the one whose links lose least uncertainty
to a drift estimated alongside wins — the worst of a linear drift and a warm-up with τ of 10,
30 or 60 min and τ estimated (``programs.design.drift_u_worst``): a warm-up bends over the run,
and an order whose time follows a quadratic in C or B confounds that bend with the links.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import numpy as np

EXHAUSTIVE_MAX = 8  # poses (the first fixed): 7! = 5 040 orders
TIE_FRACTION = 0.01
TIE_MAX = 24  # tours re-ranked by drift


def unwrap_c(c_deg: Sequence[float], travel: tuple[float, float]) -> list[float]:
    """C angles moved by whole turns so that the largest empty arc is not crossed, all within
    ``travel`` (as given when no common shift fits the travel)."""
    c = np.mod(np.asarray(c_deg, float), 360.0)
    u = np.unique(np.round(c, 9))
    if len(u) > 1:
        gaps = np.diff(np.concatenate([u, [u[0] + 360.0]]))
        start = u[(int(np.argmax(gaps)) + 1) % len(u)]  # the arc begins after the largest gap
    else:
        start = u[0]
    v = start + np.mod(c - start, 360.0)
    # one shift for all (neighbours stay neighbours), the one nearest zero that fits the travel
    fits = [v + s for s in (0.0, -360.0, 360.0, -720.0, 720.0)
            if np.all(v + s >= travel[0] - 1e-9) and np.all(v + s <= travel[1] + 1e-9)]
    if not fits:
        return [float(x) for x in c_deg]
    w = min(fits, key=lambda x: float(np.abs(x).max()))
    return [round(float(x), 6) for x in w]


def monotone(values: Sequence[float]) -> bool:
    """Sorted (either way) — a time order that follows this axis."""
    d = np.diff(np.asarray(values, float))
    return bool(np.all(d >= -1e-9) or np.all(d <= 1e-9))


def order_tour(cost: np.ndarray, c_deg: Sequence[float],
               drift_penalty: Callable[[list[int]], float] | None = None) -> list[int]:
    """Visiting order of poses 0..n-1 starting (and, for the revisit, ending) at pose 0.

    ``cost[i, j]``: seconds from pose i to pose j. Orders whose C values (``c_deg``) are
    monotone are refused when any other exists; ``drift_penalty(order)`` breaks near-ties."""
    n = len(cost)
    if n <= 2:
        return list(range(n))
    rest = np.arange(1, n)
    if n <= EXHAUSTIVE_MAX:
        perms = np.array(list(itertools.permutations(rest)))
        seq = np.column_stack([np.zeros(len(perms), int), perms, np.zeros(len(perms), int)])
        total = cost[seq[:, :-1], seq[:, 1:]].sum(axis=1)
        c = np.asarray(c_deg, float)[seq[:, :-1]]
        d = np.diff(c, axis=1)
        mono = np.all(d >= -1e-9, axis=1) | np.all(d <= 1e-9, axis=1)
        if not mono.all():
            total = np.where(mono, np.inf, total)
        rank = np.argsort(total, kind="stable")
        best = float(total[rank[0]])
        near = [int(i) for i in rank[:TIE_MAX] if total[i] <= best * (1 + TIE_FRACTION)]
        orders = [list(seq[i, :-1]) for i in near]
    else:
        orders = [_two_opt(cost, c_deg)]
    if drift_penalty is not None and len(orders) > 1:
        orders.sort(key=drift_penalty)
    return [int(x) for x in orders[0]]


def _tour_cost(cost: np.ndarray, order: list[int]) -> float:
    seq = [*order, order[0]]
    return float(sum(cost[a, b] for a, b in itertools.pairwise(seq)))


def _two_opt(cost: np.ndarray, c_deg: Sequence[float]) -> list[int]:
    """Nearest neighbour from pose 0, then 2-opt, keeping the C order non-monotone."""
    n = len(cost)
    order, left = [0], set(range(1, n))
    while left:
        j = min(left, key=lambda x: (cost[order[-1], x], x))
        order.append(j)
        left.remove(j)
    c = np.asarray(c_deg, float)

    def ok(o: list[int]) -> bool:
        return not monotone(c[o])

    if not ok(order):  # interleave: every other pose out, the rest on the way back
        order = [0, *order[1::2], *order[2::2][::-1]]
    improved = True
    while improved:
        improved = False
        for i in range(1, n - 1):
            for k in range(i + 1, n):
                cand = order[:i] + order[i:k + 1][::-1] + order[k + 1:]
                if ok(cand) and _tour_cost(cost, cand) < _tour_cost(cost, order) - 1e-9:
                    order, improved = cand, True
    return order
