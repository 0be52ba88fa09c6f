"""One analysis of measured ball centres → the ``Analysis`` shared by `rumba analyze`, daemon
runs and their reports: estimate (setup + links), volumetric distortion, clusters, validation.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from contracts.setup_files import load_machine
from contracts.yaml_files import ConfigError
from daemon.analysis.result import (
    Analysis,
    Cluster,
    Distance,
    Estimation,
    Health,
    IndexScatter,
    LinkError,
    Offset,
    Revisit,
    Scale,
    Setup,
    SphereFrame,
    Stability,
    Validation,
    VolumetricMax,
    VolumetricPoint,
    Where,
)
from daemon.analysis.thermal import corrected, thermal_block, with_thermal
from daemon.analysis.touch_centres import (
    CentreData,
    estimate_frame,
    in_frame,
    screen_centres,
    with_outliers,
)
from identification.analyses import (
    clusters,
    distance_analysis,
    revisits,
    validate,
    volumetric,
)
from identification.drift import estimate_drift_aware
from identification.estimate import RankDeficientError, estimate
from identification.estimate_scatter import visits_of
from identification.kinematics import Machine
from identification.model import Artefact, Centres
from identification.plausibility import describe, implausible
from identification.touch_frame import FrameEstimate

_THESIS = {  # thesis Table B.2 / Fig B.2 names of the WCBXFZYT link errors
    "EB0Z": "βZ squareness ZX", "EA0Y": "αY squareness YZ", "EC0Y": "γY squareness YX",
    "EA0B": "αB orientation BZ", "EC0B": "γB orientation BX", "EX0C": "δxC offset CB",
    "EA0C": "αC orientation CB", "EB0C": "βC orientation CX",
}
_GREEK = {"A": "α", "B": "β", "C": "γ"}


class AnalysisError(ConfigError):
    """The centres cannot be analysed as asked (held-out poses absent, rank deficiency, a
    numerical failure caused by the data …); a ``ConfigError``, so every ``rumba`` command
    ends on it with one ``error:`` line."""


class ImplausibleFitError(AnalysisError):
    """The fit converged to values the declared geometry cannot have (``identification.
    plausibility``): a wrong machine or artefact file, not errors to report or compensate."""


def touch_noise_um(data: CentreData) -> float | None:
    """The touches' noise as their sphere fits show it (median form residual, µm), None for
    centres without touches or touches without noise (a noise-free simulation)."""
    form = [h.form_rms_um for h in data.health if math.isfinite(h.form_rms_um)]
    noise = float(np.median(form)) if form else 0.0
    return noise if noise > 0.0 else None


def fitting_machines(paths: Sequence[Path], artefact: Artefact, centres: Centres) -> list[Path]:
    """Those of the machine files ``paths`` a plain estimate on ``centres`` fits plausibly (for
    the hint of a refusal: which machine the data were measured on); unreadable files and
    failing fits are skipped."""
    out = []
    for path in paths:
        try:
            machine, _ = load_machine(path)
            with np.errstate(all="ignore"):
                est = estimate(machine, artefact, centres)
        except (ConfigError, ValueError, np.linalg.LinAlgError, FloatingPointError):
            continue
        if np.isfinite(est.residual_rms_um) and not implausible(machine, artefact, est):
            out.append(path)
    return out


def thesis_name(iso: str) -> str:
    """The thesis' name of an ISO 230-1 location error (Greek letter for the others)."""
    if iso in _THESIS:
        return _THESIS[iso]
    kind, axis = iso[1], iso[3]
    return f"δ{kind.lower()}{axis}" if kind in "XYZ" else f"{_GREEK[kind]}{axis}"


def analyse_centres(machine: Machine, artefact: Artefact, data: CentreData, *,
                    validate_poses: Sequence[int] = (), links: Sequence[str] | None = None,
                    repeatability_um: Sequence[float] | None = None,
                    fixed_radius: bool = False, source: str = "",
                    estimator: Callable[[Centres], tuple[Any, Callable | None]] | None = None,
                    keep: dict[str, Any] | None = None,
                    rotary_repeatability_urad: Mapping[str, float] | None = None) -> Analysis:
    """The whole analysis (its ``to_json()``: the analysis contract's keys, plus a few more).

    ``links`` None: the identifiable set; () setup only. Poses in ``validate_poses`` are held
    out of the estimate and predicted (thesis annex B). ``estimator`` (centres input,
    ``daemon.analysis.centres_input``) replaces ``estimate`` on the estimation centres: it
    returns the estimate and, for centres in an instrument frame, the map to controller X Y Z
    the analyses then run in. Visits are screened for gross faults first (``screen_centres``).
    ``keep``: receives the estimate itself under "estimate" (the run's compensation view is
    planned from this very estimate, so the panel's link values are the report's)
    and under "touch_data" every visit's centre fitted in its frame (what the store and
    ``--write-centres`` keep, ``identification.touch_frame``).
    ``rotary_repeatability_urad``: the machine file's stated rotary repeatability (µrad 1σ by
    axis letter), the Type B input of the links' index scatter (``estimate_scatter``)."""
    every = data
    data, screened = screen_centres(machine, artefact, data)
    c = data.centres
    poses = sorted(int(x) for x in np.unique(c.pose))
    missing = sorted(set(validate_poses) - set(poses))
    if missing:
        raise AnalysisError(f"validation poses {missing} are not in {source or 'the data'} "
                            f"(poses {poses})")
    held = np.isin(c.pose, list(validate_poses))
    if held.all():
        raise AnalysisError("every pose is held out for validation; nothing left to estimate")
    where = f"{source}: " if source else ""
    bad = ~np.isfinite(c.xyz_mm).all(axis=1) | ~np.isfinite(c.b_deg) | ~np.isfinite(c.c_deg)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise AnalysisError(f"{where}centre of ball {artefact.ids[c.ball[k]]} pose "
                            f"{int(c.pose[k])} is not a finite number")
    drift = None  # a TCP drift fitted with the links where the timing separates it
    frame = None
    try:
        with np.errstate(all="ignore"):
            if estimator is None:
                # the touches fitted in the frame the estimate corrects (METHOD.md §7): on axes
                # out of square a sphere fitted in controller axes is off by a pose-dependent
                # bias (identification/touch_frame.py); every visit refitted, the faulty ones
                # too (their health), and handed on for the store and --write-centres
                frame = estimate_frame(machine, artefact, data, ~held, links,
                                       repeatability_um, fixed_radius)
                every = in_frame(machine, artefact, every, frame, fixed_radius)
                data = replace(in_frame(machine, artefact, data, frame, fixed_radius, False),
                               health=every.health)
                c = data.centres
            est_c = c.subset(~held)
            if estimator is None:
                drift = estimate_drift_aware(
                    machine, artefact, est_c, links, sigma_um=repeatability_um,
                    rotary_repeatability_urad=dict(rotary_repeatability_urad or {}) or None)
                est, to_machine = drift.estimate, None
            else:
                est, to_machine = estimator(est_c)
    except RankDeficientError as e:
        raise AnalysisError(f"{where}{e}") from None
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as e:
        raise AnalysisError(f"{where}estimate (setup + links) failed on these centres: "
                            f"{e}") from None
    if not (np.isfinite(est.residual_rms_um)
            and all(np.isfinite(v) for v, _, _ in est.links_si().values())):
        raise AnalysisError(f"{where}estimate (setup + links) did not converge to finite "
                            "numbers (centres far outside the machine's range?)")
    if keep is not None:
        keep["estimate"] = est
        keep["touch_data"] = every
    findings = implausible(machine, artefact, est, touch_noise_um(data))
    if findings:  # 90° "link errors" are not a machine's: refuse, never report or compensate
        raise ImplausibleFitError(f"{where}{describe(machine, artefact, findings)}")
    if to_machine is not None:
        data = replace(data, centres=replace(c, xyz_mm=to_machine(c.xyz_mm)))
        est_c = data.centres.subset(~held)
    if drift is not None and drift.fit is not None:
        data = corrected(data, drift)
        est_c = data.centres.subset(~held)
    try:
        with np.errstate(all="ignore"):
            result = _analyses(machine, artefact, data, est, est_c, held, fixed_radius,
                               frame)
            if drift is not None:
                result = with_thermal(result, thermal_block(drift))
            return with_outliers(result, screened)
    except (np.linalg.LinAlgError, FloatingPointError) as e:
        raise AnalysisError(f"{where}analysis of the estimate failed: {e}") from None


def _analyses(machine: Machine, artefact: Artefact, data: CentreData, est: Any, est_c: Any,
              held: np.ndarray, fixed_radius: bool, frame: FrameEstimate | None = None
              ) -> Analysis:
    """Volumetric, clusters, distances, stability, validation → the typed result, built once
    with the JSON's rounding (``_vec``, ``round``) and NaN/inf → None (``_fin``)."""
    c = data.centres
    ids = artefact.ids
    vol = volumetric(machine, artefact, est, c)
    pred_setup = c.xyz_mm - vol.before_um * 1e-3  # nominal machine + estimated setup
    group = c.pose * 1000 + data.repeat  # one cluster per pose and repeat
    groups = np.unique(group)
    cl = clusters(c, pred_setup, vol.before_um, ids, group)
    first = {int(g): int(np.flatnonzero(group == g)[0]) for g in groups}
    dist = distance_analysis(c, ids, group)
    balls_v, balls_s = est.balls_um
    probe_v, probe_s = est.probe_um
    pose = [int(x) for x in c.pose.tolist()]
    repeat = [int(x) for x in np.asarray(data.repeat).tolist()]
    b_deg = np.asarray(c.b_deg, dtype=float).tolist()
    c_deg = np.asarray(c.c_deg, dtype=float).tolist()
    ball = [ids[i] for i in c.ball.tolist()]
    out = held.tolist()
    before, after = _vecs(vol.before_um), _vecs(vol.after_um)
    rv = revisits(c, data.repeat, ids)
    stability = None
    if rv:
        worst = max(rv, key=lambda r: r.norm_um)
        stability = Stability(
            convention="ball centre at its last visit − at its first visit of the same "
                       "pose, controller X Y Z, µm (thermal drift, loose ball, probe drift)",
            max_shift_um=_fin(round(worst.norm_um, 4)),
            worst=Where(pose=worst.pose, ball=worst.ball),
            span_min=_fin(round(max(r.dt_s for r in rv) / 60.0, 3)),
            revisits=tuple(Revisit(pose=r.pose, ball=r.ball,
                                   repeats=(r.repeat_first, r.repeat_last),
                                   dt_min=_fin(round(r.dt_s / 60.0, 3)), shift_um=_vec(r.shift_um),
                                   norm_um=_fin(round(r.norm_um, 4))) for r in rv))
    sc = est.scale_um_per_m
    validation = None
    if held.any():
        val = validate(machine, artefact, est, c.subset(held))
        validation = Validation(
            poses=tuple(_fin(p) for p in val.poses),
            rms_before_um=_fin(round(val.rms_before_um, 4)),
            rms_after_um=_fin(round(val.rms_after_um, 4)),
            max_before_um=_fin(round(val.max_before_um, 4)),
            max_after_um=_fin(round(val.max_after_um, 4)),
            explained_fraction=_fin(round(val.explained_fraction, 4)),
            explained_fraction_rms=_fin(round(val.explained_fraction_rms, 4)))
    return Analysis(
        machine=machine.name, topology=machine.topology, artefact=artefact.name,
        links={k: LinkError(value=_fin(round(v, 4)), std=_fin(round(s, 4)), unit=u,
                            thesis_name=thesis_name(k))
               for k, (v, s, u) in est.links_si().items()},
        setup=Setup(probe=Offset(value=_vec(probe_v), std=_vec(probe_s)),
                    balls={b: Offset(value=_vec(balls_v[i]), std=_vec(balls_s[i]))
                           for i, b in enumerate(ids)}),
        residual_rms_um=_fin(round(est.residual_rms_um, 4)),
        condition_number=_fin(round(est.condition_number, 3)),
        unobservable=tuple(_fin(u) for u in est.unobservable),
        unobservable_absorbed_by={k: _fin(v) for k, v in dict(est.absorbed_by).items()},
        estimation=Estimation(
            status=est.status, iterations=est.iterations, centres=len(est_c),
            sigma_um=_vec(est.sigma_um),
            sigma_from="given" if est.sigma_given else "residuals",
            sigma_dof=_fin(est.sigma_dof),  # None (JSON) when given: infinite
            fixed_radius=fixed_radius,
            index_scatter=index_scatter(est.visit_scatter, est.stated_used,
                                        len(np.unique(visits_of(est_c)))),
            sphere_frame=None if frame is None else SphereFrame(
                passes=frame.passes, max_shift_um=_fin(round(frame.shift_um, 4)),
                note=frame.note)),
        volumetric=tuple(
            VolumetricPoint(pose=pose[k], repeat=repeat[k], b_deg=_fin(b_deg[k]),
                            c_deg=_fin(c_deg[k]), ball=ball[k],
                            role="validate" if out[k] else "estimate", held_out=out[k],
                            error_um=before[k], error_after_links_um=after[k])
            for k in range(len(c))),
        volumetric_max_um=VolumetricMax(before_links=_fin(round(vol.max_before_um, 4)),
                                        after_links=_fin(round(vol.max_after_um, 4))),
        cluster=tuple(
            Cluster(pose=x.pose, repeat=repeat[first[int(g)]], b_deg=_fin(b_deg[first[int(g)]]),
                    c_deg=_fin(c_deg[first[int(g)]]),
                    linear_um=None if x.linear_um is None else _vec(x.linear_um),
                    angular_urad=None if x.angular_urad is None else _vec(x.angular_urad),
                    local_um={b: _vec(v) for b, v in x.local_um.items()}, note=x.note)
            for x, g in zip(cl, groups, strict=True)),
        distances=tuple(Distance(pose=d.pose, balls=(d.ball_a, d.ball_b),
                                 distance_mm=_fin(round(d.distance_mm, 7)),
                                 deviation_um=_fin(round(d.deviation_um, 4))) for d in dist),
        health=tuple(Health(pose=h.pose, repeat=h.repeat, ball=h.ball,
                            radius_dev_um=_fin(round(h.radius_dev_um, 4)),
                            form_rms_um=_fin(round(h.form_rms_um, 4))) for h in data.health),
        warnings=(*data.warnings, *est.warnings),
        conventions=dict(CONVENTIONS),
        stability=stability,
        scale_um_per_m=None if sc is None else Scale(value=_fin(round(sc[0], 4)),
                                                    std=_fin(round(sc[1], 4))),
        validation=validation)


CONVENTIONS = {
    "volumetric": "measured − predicted centre, controller X Y Z, µm (thesis Eq. 3.22)",
    "cluster": "rigid motion predicted → measured: ε ≈ linear + angular × P (P: predicted "
               "centre, mm, controller origin); the thesis' D, R of Eq. 4.4 are the negatives; "
               "local = ε − rigid part",
    "setup": "ball offsets in the last workpiece frame, probe offset in the last tool frame, µm",
    "std": "standard uncertainty u; with σ from the residuals (estimation.sigma_dof = ν) the "
           "standard deviation of the Student t of the estimate, s·√(ν/(ν−2)) (GUM-S1 "
           "6.4.9.4): ±2u covers ≥ 95 %; the judge and the compensation expand it with the t "
           "quantile over that factor (identification/uncertainty.py); with a drift model "
           "(thermal) it also carries the model choice",
}
"""What the numbers of an analysis mean (its JSON's ``conventions``)."""


def index_scatter(comps: dict[str, tuple[float, float, float]] | None,
                  stated_used: tuple[str, ...] = (), visits: int | None = None
                  ) -> tuple[IndexScatter, ...] | None:
    """The estimate's index components per rotary axis (``Estimate.visit_scatter``): the free
    REML estimate and, with a stated repeatability, the stated value and the test's p; which
    one the links' u rests on is the estimator's decision (``Estimate.stated_used``, made in
    ``identification.estimate_scatter.with_stated``), carried here, never re-derived."""
    if not comps:
        return None
    out = []
    for name, (v, u, p) in comps.items():
        if not name.startswith("index ") or name.endswith(" stated"):
            continue
        st = comps.get(f"{name} stated")
        used = "stated" if name in stated_used else "estimated"
        out.append(IndexScatter(axis=name[6:], estimated_urad=_fin(round(v, 3)),
                                std_urad=_fin(round(u, 3)), p_value=_fin(float(f"{p:.3g}")),
                                stated_urad=None if st is None else st[0],
                                p_stated=None if st is None else float(f"{st[2]:.3g}"),
                                used=used, visits=visits))
    return tuple(out)


def _fin(x: Any) -> Any:
    """A float that is NaN or inf → None (JSON has neither); anything else as it is."""
    return None if isinstance(x, float) and not math.isfinite(x) else x


def _vec(a: Any) -> tuple[float | None, ...]:
    """A vector as the JSON holds it: each value rounded to 1e-6, None where not finite."""
    return tuple(_fin(round(x, 6)) for x in np.asarray(a, dtype=float).ravel().tolist())


def _vecs(a: np.ndarray) -> list[tuple[float | None, ...]]:
    """``_vec`` of each row of ``a`` (one conversion to Python floats for the whole array)."""
    rows = np.asarray(a, dtype=float).reshape(len(a), -1).tolist()
    return [tuple(_fin(round(x, 6)) for x in row) for row in rows]
