"""Probing-log touches → one sphere centre per (run, repeat, pose, ball), with fit health, the
outlier test that decides which of those visits an estimate uses, and the refit of the centres in
the frame the estimate corrects (``identification.touch_frame``)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

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
from daemon.analysis.result import Analysis, Outlier, OutlierTest
from identification.kinematics import Machine
from identification.model import Artefact, Centres
from identification.outliers import (
    CENTRE_Z,
    MIN_SIZE_UM,
    SPHERE_Z,
    find_outliers,
    resolve,
)
from identification.spherefit import SphereFitError, centre_sensitivity, fit_spheres
from identification.touch_frame import FrameEstimate, frame_estimate, refit


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
    points_mm: np.ndarray | None = None  # (G, 5, 3) latched touches 1..5 (outlier test)
    radius_nominal_mm: np.ndarray | None = None  # (G,) ball + stylus radius


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
    touch_t = col["t_s"][idx]
    centres = Centres(uniq[:, 1].copy(), uniq[:, 2].copy(), b_g.mean(axis=1), c_g.mean(axis=1),
                      fit.centre_mm, touch_t.mean(axis=1), touch_t,
                      centre_sensitivity(pts, fit.centre_mm, fixed_radius))
    return CentreData(centres, uniq[:, 0].copy(), health, msgs, pts, r_nom)


def estimate_frame(machine: Machine, artefact: Artefact, data: CentreData,
                   estimation: np.ndarray, links: Sequence[str] | None = None,
                   sigma_um: Sequence[float] | None = None, fixed_radius: bool = False
                   ) -> FrameEstimate | None:
    """The frame the touches of ``data`` are fitted in (``identification.touch_frame``,
    estimated on the visits of the mask ``estimation``); None for centres without touches."""
    if data.points_mm is None or data.radius_nominal_mm is None:
        return None
    return frame_estimate(machine, artefact, data.centres, data.points_mm,
                          data.radius_nominal_mm, estimation, links, sigma_um=sigma_um,
                          fixed_radius=fixed_radius)


def in_frame(machine: Machine, artefact: Artefact, data: CentreData,
             frame: FrameEstimate | None, fixed_radius: bool = False,
             health: bool = True) -> CentreData:
    """``data`` with every visit fitted again in ``frame`` (``estimate_frame``): centres, their
    touch sensitivities and, with ``health``, the health of those visits (radius and form of
    the true ball; matched by the log's repeat, pose and ball, so not for visits the outlier
    screen renumbered); unchanged without touches or when the frame stayed the controller's."""
    if (frame is None or frame.layout is None or data.points_mm is None
            or data.radius_nominal_mm is None or not len(data.centres)):
        return data
    c, ff = refit(machine, frame.layout, frame.p, data.centres, data.points_mm,
                  data.radius_nominal_mm, fixed_radius)
    if not health:
        return replace(data, centres=c)
    ids = artefact.ids
    new = {(int(r), int(p), ids[int(b)]): k
           for k, (r, p, b) in enumerate(zip(data.repeat, c.pose, c.ball, strict=True))}
    health = []
    for h in data.health:
        k = new.get((h.repeat, h.pose, h.ball))
        health.append(h if k is None else replace(
            h, radius_dev_um=float(ff.fit.radius_dev_um[k]),
            form_rms_um=float(ff.fit.form_rms_um[k])))
    return replace(data, centres=c, health=health)


OUTLIER_METHOD = ("per ball visit, against the run's own median and MAD × 1.4826: D from the "
                  "free sphere fit's radius and form residual; z_c (one-sided) from the "
                  "centre's deleted residual against setup + location errors + a creep of "
                  "each ball, minus the median of the other balls of the same pass, along the "
                  "pole normal; identification/outliers.py")


def describe_outlier(ball: str, pose: int, repeat: int, touch: int, size_um: float) -> str:
    """'ball B2 pose 7 touch 2 (+10.3 µm)': a visit and its fault, as every message names it."""
    rep = f" repeat {repeat}" if repeat else ""
    return f"ball {ball} pose {pose}{rep} touch {touch} ({size_um:+.1f} µm)"


def screen_centres(machine: Machine, artefact: Artefact, data: CentreData
                   ) -> tuple[CentreData, dict[str, Any] | None]:
    """The outlier test of every visit (``identification.outliers``) and the visits the
    estimate uses: a faulty visit is left out, a clean re-probe stands for the visit it
    re-measures (repeat of the original), a re-probe of a clean visit is not used. Returns
    that ``CentreData`` (health and warnings of every visit kept) and the analysis JSON parts
    ``outlier_test`` and ``outliers`` (None without touch points: centres given as such)."""
    if data.points_mm is None or data.radius_nominal_mm is None:
        return data, None
    c, ids = data.centres, artefact.ids
    scr = find_outliers(machine, artefact, c, data.points_mm, data.radius_nominal_mm,
                        data.repeat)
    res = resolve(data.repeat, c.pose, c.ball, [o.index for o in scr.outliers])
    outliers, msgs = [], []
    for o in sorted(scr.outliers, key=lambda o: (int(c.pose[o.index]), int(c.ball[o.index]),
                                                 int(data.repeat[o.index]))):
        k = o.index
        status = res.status[k]
        by = res.replaced_by.get(k)
        by_repeat = int(data.repeat[by]) if by is not None else None
        what = describe_outlier(ids[int(c.ball[k])], int(c.pose[k]), int(data.repeat[k]),
                                o.touch, o.size_um)
        fate = {"repaired": f"repaired: the re-probe (repeat {by_repeat}) is used instead",
                "unrepaired": "left out of the estimate; the measurement is not trusted until "
                              "the ball is cleaned and probed again",
                "not used": "a re-probe that met a fault; the clean first visit is used"}
        msgs.append(f"measurement outlier at {what}: the touch latched "
                    f"{'outside' if o.size_um > 0 else 'inside'} the sphere the rest of the run "
                    f"predicts (chip, dirt, coolant or a bad trigger; robust z {o.score:.0f}); "
                    f"{fate[status]}")
        outliers.append({"pose": int(c.pose[k]), "ball": ids[int(c.ball[k])],
                         "repeat": int(data.repeat[k]), "touch": o.touch,
                         "size_um": round(o.size_um, 3), "score": round(o.score, 2),
                         "stage": o.stage, "status": status, "replaced_by_repeat": by_repeat})
    if scr.note:
        msgs.append(f"outlier test: {scr.note}")
    test = {"method": OUTLIER_METHOD, "visits": scr.visits, "sphere_z": SPHERE_Z,
            "centre_z": CENTRE_Z, "min_size_um": MIN_SIZE_UM,
            "radius_scale_um": _r(scr.radius_scale_um), "form_scale_um": _r(scr.form_scale_um),
            "centre_scale_um": _r(scr.centre_scale_um), "note": scr.note}
    u = res.use
    used = CentreData(c.subset(u), res.repeat[u], data.health, [*data.warnings, *msgs],
                      data.points_mm[u], data.radius_nominal_mm[u])
    return used, {"outlier_test": test, "outliers": outliers}


def with_outliers(analysis: Analysis, parts: dict[str, Any] | None) -> Analysis:
    """``analysis`` with the outlier test's JSON parts (``screen_centres``) typed in."""
    if parts is None:
        return analysis
    return replace(analysis, outlier_test=OutlierTest.from_json(parts["outlier_test"]),
                   outliers=tuple(Outlier.from_json(o) for o in parts["outliers"]))


def _r(x: float | None) -> float | None:
    return None if x is None else round(float(x), 4)
