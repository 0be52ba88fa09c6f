"""Visiting order of the balls at one pose: a short open tour through their centres."""

from __future__ import annotations

import itertools

import numpy as np


def open_tour(points: np.ndarray, start: np.ndarray) -> list[int]:
    """Open tour through ``points`` from ``start`` (unknown: NaN → best of every first point):
    nearest neighbour, then 2-opt (a handful of balls: this finds the optimum in practice)."""
    n = len(points)
    known = not np.any(np.isnan(start))

    def length(o: list[int]) -> float:
        seq = ([start] if known else []) + [points[i] for i in o]
        return sum(float(np.linalg.norm(a - b)) for a, b in itertools.pairwise(seq))

    def improve(order: list[int]) -> list[int]:
        lo = 0 if known else 1  # with an unknown start the first point is the choice
        improved = True
        while improved:
            improved = False
            for i in range(lo, n - 1):
                for k in range(i + 1, n):
                    cand = order[:i] + order[i:k + 1][::-1] + order[k + 1:]
                    if length(cand) < length(order) - 1e-9:
                        order, improved = cand, True
        return order

    def nearest(first: int | None) -> list[int]:
        left = set(range(n))
        order: list[int] = []
        cur = start
        if first is not None:
            order, cur = [first], points[first]
            left.remove(first)
        while left:
            j = min(left, key=lambda i: (round(float(np.linalg.norm(points[i] - cur)), 9), i))
            order.append(j)
            left.remove(j)
            cur = points[j]
        return order

    if known:
        return improve(nearest(None))
    tours = [improve(nearest(f)) for f in range(n)]
    return min(tours, key=lambda o: (round(length(o), 6), o))
