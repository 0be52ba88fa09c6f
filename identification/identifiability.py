"""Which link errors a pose set can identify together with the setup errors (METHOD.md §2).

The full location-error Jacobian is built with the setup columns; columns are then kept greedily
in a fixed priority order — setup first (always estimated), then rotary-axis errors, then the
linear axes of the tool branch, then those of the workpiece branch — whenever they raise the
numerical rank (a pivoted QR restricted to that order). For WCBXFZYT this keeps exactly the
eight errors of thesis Table B.2 and names what each dropped column is absorbed by.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict

RANK_TOL = 1e-7  # relative to the largest singular value of the unit-norm-column Jacobian


@dataclass(frozen=True)
class Identifiability:
    """The selected link set and what was found unobservable (with what absorbs it)."""

    links: tuple[str, ...]
    dropped: dict[str, str]  # link → the kept columns it is a combination of
    scale_observable: bool


def nominal_centres(machine: Machine, artefact: Artefact, poses: list[tuple[float, float]]
                    ) -> Centres:
    """Centres the nominal machine would measure for every (pose, ball)."""
    n = len(artefact.balls)
    pose = np.repeat(np.arange(len(poses)), n)
    ball = np.tile(np.arange(n), len(poses))
    bc = np.array(poses, float)[pose]
    c = Centres(pose, ball, bc[:, 0], bc[:, 1], np.zeros((len(pose), 3)))
    layout = Layout((), n)
    c.xyz_mm, _ = predict(machine, artefact, layout, np.zeros(layout.size), c)
    return c


def _unit_columns(j: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(j, axis=0)
    return j / np.where(norms > 0, norms, 1.0)


def numerical_rank(j: np.ndarray) -> int:
    """Rank of ``j`` with unit-norm columns, singular values below RANK_TOL relative dropped."""
    if j.shape[1] == 0:
        return 0
    s = np.linalg.svd(_unit_columns(j), compute_uv=False)
    return int(np.sum(s > RANK_TOL * s[0])) if s[0] > 0 else 0


def explain_absorption(col: np.ndarray, basis: np.ndarray, names: list[str]) -> str:
    """What absorbs a dropped column: the (up to three) ``names`` of ``basis`` columns that
    carry most of its least-squares combination."""
    if not np.any(col):
        return "nothing: no effect on the measured centres for these poses"
    coef, *_ = np.linalg.lstsq(basis, col, rcond=None)
    scale = np.abs(coef) * np.linalg.norm(basis, axis=0)
    top = [names[i] for i in np.argsort(scale)[::-1] if scale[i] > 1e-6 * scale.max()][:3]
    return " + ".join(top)


def identifiable_links(machine: Machine, artefact: Artefact, centres: Centres,
                       with_distances: bool | None = None) -> Identifiability:
    """Select the identifiable location errors for this machine, artefact and pose set."""
    candidates = machine.location_error_names()
    full = Layout(tuple(candidates), len(artefact.balls), scale=True)
    _, jac = predict(machine, artefact, full, np.zeros(full.size), centres, jacobian=True)
    j = jac.reshape(-1, full.size)
    names = full.names(artefact.ids)
    setup_cols = list(range(len(candidates), full.size - 1))
    kept = list(setup_cols)
    dropped: dict[str, str] = {}
    if numerical_rank(j[:, kept]) < len(kept):
        raise ValueError("setup errors alone are not identifiable from these poses "
                         "(too few poses or balls; need at least two distinct indexations)")
    for i, name in enumerate(candidates):
        if numerical_rank(j[:, [*kept, i]]) > len(kept):
            kept.append(i)
        else:
            dropped[name] = explain_absorption(j[:, i], j[:, kept], [names[k] for k in kept])
    scale_col = full.size - 1
    use_dist = bool(artefact.distances) if with_distances is None else with_distances
    scale_observable = use_dist or numerical_rank(j[:, [*kept, scale_col]]) > len(kept)
    links = tuple(candidates[i] for i in kept if i < len(candidates))
    return Identifiability(links, dropped, scale_observable)
