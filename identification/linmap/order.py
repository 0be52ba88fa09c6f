"""The polynomial degree of each axis' map, chosen from the data by cross-validation over visits.

The model is linear in its parameters to well below a nanometre at the sizes involved (µm
errors, sub-mm setups), so the choice runs on the problem linearised at a preliminary fit with
every observable term up to the cap: y ≈ J p (weighted rows; the Tikhonov prior of the fit as
extra rows). For every combination of degrees (0 = no map for that axis, up to the cap) the map
terms of degree ≤ the axis' degree are fitted with links and setups on all visits but one fold
and predict the visits of that fold; the folds are whole visits (every ball of one indexation:
they share its index error and any drift, so a fold never sees a correlated twin of a held-out
centre). Rule: of the combinations whose pooled held-out weighted squared error is not
significantly above the least one (the mean per-visit difference within ``SE_RULE`` standard
errors of it, visits being the independent units), the one with the most terms. A degree too
low leaves a bias the stated u does not know (measured on simulated maps of the swivel head:
the least-error choice cut Z to degree 2 of a degree-4 truth in some seeds, 75 % 2u coverage;
one degree too many only widens u, which is stated), so near-ties go to the larger model.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

N_FOLDS = 5
SE_RULE = 1.0


@dataclass(frozen=True)
class OrderChoice:
    degrees: dict[str, int]  # per linear axis, 0: no map terms
    method: str
    # every combination tried: (degrees X, Y, Z) → held-out RMS of the weighted residuals
    scores: dict[tuple[int, int, int], float]


def keep_count(ax: np.ndarray, deg: np.ndarray, d: dict[str, int]) -> np.ndarray:
    """Per column: a map term of degree ≤ its axis' degree in ``d``."""
    return np.array([bool(a) and k <= d[a] for a, k in zip(ax, deg, strict=True)])


def fold_of(groups: np.ndarray, n_folds: int = N_FOLDS) -> np.ndarray:
    """Fold index per row: the unique ``groups`` (visits) dealt to folds in a fixed shuffled
    order (seeded: the same data give the same folds on every run); −1 groups are never held
    out (the calibrated distances)."""
    ids = np.unique(groups[groups >= 0])
    perm = np.random.default_rng(0).permutation(len(ids))
    k = min(n_folds, len(ids))
    where = {int(g): int(perm[i] % k) for i, g in enumerate(ids)}
    return np.array([where.get(int(g), -1) for g in groups])


def choose_degrees(jw: np.ndarray, yw: np.ndarray, groups: np.ndarray, prior: np.ndarray,
                   term_axis: Sequence[str | None], term_degree: Sequence[int],
                   max_degree: int, n_folds: int = N_FOLDS) -> OrderChoice:
    """``jw`` (rows, P), ``yw`` (rows,) the weighted linear model in absolute parameters;
    ``groups`` the visit of each row (−1: never held out); ``prior`` (P,) the diagonal of the
    Tikhonov term (0 for links and setup); ``term_axis``/``term_degree`` per column (None for
    a column that is always fitted)."""
    fold = fold_of(groups, n_folds)
    folds = sorted(set(fold.tolist()) - {-1})
    axes = [a for a in "XYZ" if a in set(t for t in term_axis if t is not None)]
    top = {a: max([d for t, d in zip(term_axis, term_degree, strict=True) if t == a],
                  default=0) for a in "XYZ"}
    lam = np.diag(prior)
    parts = []
    for f in folds:
        tr, te = fold != f, fold == f
        a_mat = jw[tr].T @ jw[tr] + lam
        parts.append((a_mat, jw[tr].T @ yw[tr], jw[te], yw[te]))
    always = np.array([t is None for t in term_axis])
    ax = np.array([t or "" for t in term_axis])
    deg = np.asarray(term_degree)
    scores: dict[tuple[int, int, int], float] = {}
    per_visit: dict[tuple[int, int, int], np.ndarray] = {}
    vid = np.unique(groups[fold >= 0], return_inverse=True)[1]
    n_vis = int(vid.max()) + 1 if vid.size else 0
    ranges = [range(0, min(max_degree, top[a]) + 1) if a in axes else range(0, 1) for a in "XYZ"]
    n_rows = sum(len(p[3]) for p in parts)
    for combo in itertools.product(*ranges):
        d = dict(zip("XYZ", combo, strict=True))
        keep = always | np.array([bool(a) and k <= d[a] for a, k in zip(ax, deg, strict=True)])
        s = np.flatnonzero(keep)
        sq = np.zeros(len(yw))
        for (a_mat, b, j_te, y_te), f in zip(parts, folds, strict=True):
            try:
                x = np.linalg.solve(a_mat[np.ix_(s, s)], b[s])
            except np.linalg.LinAlgError:
                x = np.linalg.lstsq(a_mat[np.ix_(s, s)], b[s], rcond=None)[0]
            sq[fold == f] = (y_te - j_te[:, s] @ x) ** 2
        per_visit[combo] = np.bincount(vid, weights=sq[fold >= 0], minlength=n_vis)
        scores[combo] = float(np.sqrt(sq.sum() / max(n_rows, 1)))
    least = min(scores, key=lambda c: (scores[c], sum(c)))
    size = {c: int(sum(keep_count(ax, deg, dict(zip("XYZ", c, strict=True))))) for c in scores}

    def tied(c: tuple[int, int, int]) -> bool:
        diff = per_visit[c] - per_visit[least]
        se = float(np.std(diff, ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else 0.0
        return float(np.mean(diff)) <= SE_RULE * se

    best = max((c for c in scores if tied(c)), key=lambda c: (size[c], -scores[c]))
    method = (f"{len(folds)}-fold cross-validation over visits (whole indexations held out), "
              f"degrees 0..{max_degree} per axis, every combination; of those whose held-out "
              f"weighted squared error is within {SE_RULE:g} standard error (over visits) of "
              "the least, the one with the most terms")
    return OrderChoice(dict(zip("XYZ", best, strict=True)), method, scores)
