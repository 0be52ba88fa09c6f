"""Probing-log touches → one sphere centre per (run, repeat, pose, ball), with fit health."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from contracts.probing_log import (
    COLUMN_TYPES,
    ROTARY_SPREAD_DEG,
    TOUCHES_PER_BALL,
    LogRow,
    ProbeLog,
    ProbeLogError,
    ProbeLogWarning,
)
from identification.model import Artefact, Centres
from identification.spherefit import SphereFitError, fit_spheres


@dataclass(frozen=True)
class GroupHealth:
    """Sphere-fit health of one (run, repeat, pose, ball)."""

    run_id: str
    repeat: int
    pose: int
    ball: str
    radius_dev_um: float
    form_rms_um: float


@dataclass
class CentreData:
    """Centres fitted from a log, one per (run, repeat, pose, ball), in ``centres`` order."""

    centres: Centres
    repeat: np.ndarray
    health: list[GroupHealth]
    warnings: list[str]


_NEEDED = ("run_id", "repeat", "pose", "ball", "touch", "x_mm", "y_mm", "z_mm", "b_deg",
           "c_deg", "t_s")


def columns(rows: Sequence[LogRow], names: Sequence[str] = _NEEDED) -> dict[str, np.ndarray]:
    """Columns of ``rows`` as numpy arrays (straight from a ``ProbeLog``, no row objects)."""
    if isinstance(rows, ProbeLog):
        return {h: rows.column(h) for h in names}
    dtype = {"str": object, "float": float, "int": int}
    return {h: np.array([getattr(r, h) for r in rows], dtype[COLUMN_TYPES[h]]) for h in names}


def one_run_balls(col: dict[str, np.ndarray], artefact: Artefact, source: str,
                  verb: str) -> tuple[list[str], np.ndarray]:
    """The log's run ids (one at most: setups differ between runs) and each row's ball index in
    the artefact; ``ProbeLogError`` naming several runs or an unknown ball id."""
    runs = sorted(set(col["run_id"].tolist()))
    if len(runs) > 1:
        raise ProbeLogError(f"{source}: contains runs {runs}; {verb} one run at a time")
    order = {b: i for i, b in enumerate(artefact.ids)}
    unknown = sorted(set(col["ball"].tolist()) - set(order))
    if unknown:
        raise ProbeLogError(f"{source}: unknown ball id(s) {unknown} (artefact {artefact.name} "
                            f"has {list(artefact.ids)})")
    return runs, np.array([order[b] for b in col["ball"]], int)


def rows_to_centres(rows: Sequence[LogRow], artefact: Artefact, stylus_radius_mm: float,
                    fixed_radius: bool = False, source: str = "log") -> CentreData:
    """Fit one centre per (run, repeat, pose, ball); incomplete groups are dropped with a
    ``ProbeLogWarning``. Several runs in one log are an error (setups differ between runs)."""
    col = columns(rows)
    runs, ball = one_run_balls(col, artefact, source, "analyse")
    touch = col["touch"]
    if len(touch) and not np.all((touch >= 1) & (touch <= TOUCHES_PER_BALL)):
        raise ProbeLogError(f"{source}: touch numbers outside 1..{TOUCHES_PER_BALL}")
    keys = np.stack([col["repeat"], col["pose"], ball], axis=1).reshape(-1, 3)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)  # sorted: repeat, pose, ball
    slot = inv.reshape(-1) * TOUCHES_PER_BALL + touch - 1
    if np.bincount(slot, minlength=1).max(initial=0) > 1:
        g = uniq[inv.reshape(-1)[np.argmax(np.bincount(slot)[slot] > 1)]]
        raise ProbeLogError(f"{source}: ball {artefact.ids[g[2]]} pose {g[1]} repeat {g[0]}: "
                            "a touch number appears twice")
    idx = np.full((len(uniq), TOUCHES_PER_BALL), -1)
    idx.reshape(-1)[slot] = np.arange(len(slot))
    msgs = []
    for (rep, pose, b), have in zip(uniq, idx >= 0, strict=True):
        if not have.all():
            msgs.append(f"{source}: ball {artefact.ids[b]} pose {pose} repeat {rep}: only "
                        f"touches {[int(t) + 1 for t in np.flatnonzero(have)]} of "
                        f"1..{TOUCHES_PER_BALL}; this ball-pose is left out")
    complete = np.all(idx >= 0, axis=1)
    uniq, idx = uniq[complete], idx[complete]
    b_g, c_g = col["b_deg"][idx], col["c_deg"][idx]
    spread = np.maximum(np.ptp(b_g, axis=1), np.ptp(c_g, axis=1)) if len(idx) else b_g[:, 0]
    if np.any(spread > ROTARY_SPREAD_DEG):
        k = int(np.argmax(spread > ROTARY_SPREAD_DEG))
        rep, pose, b = uniq[k]
        raise ProbeLogError(f"{source}: ball {artefact.ids[b]} pose {pose} repeat {rep}: latched "
                            f"b/c differ by {spread[k]:.4f}° between touches "
                            "(the rotary axes moved during probing)")
    for m in msgs:
        warnings.warn(m, ProbeLogWarning, stacklevel=2)
    if not len(uniq):
        raise ProbeLogError(f"{source}: no ball-pose has all {TOUCHES_PER_BALL} touches")
    pts = np.stack([col["x_mm"], col["y_mm"], col["z_mm"]], axis=1)[idx]  # (G, 5, 3)
    r_nom = np.array([artefact.balls[b].diameter_mm / 2 for b in uniq[:, 2]]) + stylus_radius_mm
    try:
        fit = fit_spheres(pts, r_nom, fixed_radius=fixed_radius)
    except SphereFitError as e:
        where = ""
        if e.groups:
            rep, pose, b = uniq[e.groups[0]]
            where = f"ball {artefact.ids[b]} pose {pose} repeat {rep}: "
        raise ProbeLogError(f"{source}: {where}sphere fit failed: {e.reason}") from None
    health = [GroupHealth(runs[0], int(rep), int(pose), artefact.ids[b],
                          float(fit.radius_dev_um[i]), float(fit.form_rms_um[i]))
              for i, (rep, pose, b) in enumerate(uniq)]
    centres = Centres(uniq[:, 1].copy(), uniq[:, 2].copy(), b_g.mean(axis=1), c_g.mean(axis=1),
                      fit.centre_mm, col["t_s"][idx].mean(axis=1))
    return CentreData(centres, uniq[:, 0].copy(), health, msgs)
