"""A run's compensation view (estimate with its covariance, plan), computed once at run end."""

# Stored with the run's analysis (table ``link_estimates``, migration 6): the run's stored
# centres (validation poses held out, as the run did) estimated against the controller model
# the run ran on, with the whole covariance of the links and the setup, and the plan of
# controller changes holding those links (heavy work never on the event loop; each
# is ≈ 0.1 s for 14 poses). A stored view is keyed by what it depends on besides the run's
# centres (the model, the artefact, the held-out poses, the controller values and the coverage
# factor): a machine or artefact file edited since, or a journal whose earlier compensations
# read otherwise, gives another key and the view is computed again and replaced. Runs
# journaled before migration 6 (no row) are computed on first use and stored.

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import sqlite3
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from daemon.machines.setup import MachineSetup
from daemon.store.compensation_rows import link_view, save_link_view
from daemon.store.journal import Store
from identification.compensation import (
    CompensationPlan,
    ControllerParam,
    ParamChange,
    plan_compensation,
)
from identification.estimate import Estimate, RankDeficientError, estimate
from identification.kinematics import Machine
from identification.model import Centres, Layout

FORMAT = 1  # of the stored JSON; part of the key, so a new format is computed again


class CompensationRefused(Exception):
    """A compensation the guards or the run's quality forbid; one line, exit 2, journaled."""


def centres_of(setup: MachineSetup, rows: Sequence[tuple], run_id: str) -> Centres:
    """Centre rows as the journal keeps them (pose, ball, b, c, x, y, z, …), in the journal's
    order (pose, ball), as the model's ``Centres``."""
    if not rows:
        raise CompensationRefused(f"run {run_id} has no stored centres (not identified)")
    ids = setup.artefact.ids
    unknown = sorted({r[1] for r in rows} - set(ids))
    if unknown:
        raise CompensationRefused(f"run {run_id}: balls {unknown} are not on artefact "
                                  f"{setup.artefact.name}")
    rows = sorted(rows, key=lambda r: (int(r[0]), str(r[1])))  # SQLite's ORDER BY pose, ball
    return Centres(np.array([r[0] for r in rows]), np.array([ids.index(r[1]) for r in rows]),
                   np.array([r[2] for r in rows], float), np.array([r[3] for r in rows], float),
                   np.array([r[4:7] for r in rows], float))


def run_centres(setup: MachineSetup, store: Store, run_id: str) -> Centres:
    return centres_of(setup, store.centres(run_id), run_id)


def estimation_centres(setup: MachineSetup, c: Centres) -> Centres:
    """The centres the run estimated from: its validation poses held out."""
    return c.subset(~np.isin(c.pose, list(setup.validate_poses)))


def identify(setup: MachineSetup, c: Centres, run_id: str, machine: Machine) -> Estimate:
    """The estimate of the estimation centres ``c`` against ``machine`` (the ≈ 0.1–0.4 s)."""
    try:
        with np.errstate(all="ignore"):
            return estimate(machine, setup.artefact, c, None, rotary_repeatability_urad=setup
                            .machine_file.rotary_repeatability_urad)
    except (RankDeficientError, np.linalg.LinAlgError, ValueError) as e:
        raise CompensationRefused(f"run {run_id}: identification failed: {e}") from None


def model_key(setup: MachineSetup, machine: Machine, params: Sequence[ControllerParam],
              coverage_k: float) -> str:
    """What a stored view depends on besides the run's centres, hashed."""
    text = repr((FORMAT, machine, setup.artefact, sorted(setup.validate_poses), tuple(params),
                 float(coverage_k)))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def compute(setup: MachineSetup, c: Centres, run_id: str, machine: Machine,
            params: Sequence[ControllerParam], coverage_k: float
            ) -> tuple[Estimate, CompensationPlan]:
    """The estimate of the estimation centres ``c`` and the plan of controller changes."""
    est = identify(setup, c, run_id, machine)
    plan = plan_compensation(machine, setup.artefact, est, params, c.b_deg, c.c_deg,
                             coverage_k=coverage_k)
    return est, plan


# -------------------------------------------------------------------------- stored form


def _arr(a: np.ndarray) -> dict[str, Any]:
    return {"shape": list(np.shape(a)), "v": [float(x) for x in np.ravel(a)]}


def _unarr(d: dict[str, Any]) -> np.ndarray:
    return np.array(d["v"], float).reshape(d["shape"])


def to_json(est: Estimate) -> str:
    """The whole estimate as JSON text; floats as Python writes them (repr: they read back
    bit for bit), NaN and infinities included."""
    return json.dumps({
        "format": FORMAT, "links": list(est.layout.links), "n_balls": est.layout.n_balls,
        "scale": est.layout.scale, "ball_ids": list(est.ball_ids), "p": _arr(est.p),
        "std": _arr(est.std), "cov": _arr(est.cov), "residual_mm": _arr(est.residual_mm),
        "distance_residual_um": _arr(est.distance_residual_um),
        "residual_rms_um": float(est.residual_rms_um),
        "condition_number": float(est.condition_number), "sigma_um": _arr(est.sigma_um),
        "sigma_given": bool(est.sigma_given), "iterations": int(est.iterations),
        "converged": bool(est.converged), "status": est.status,
        "unobservable": list(est.unobservable), "absorbed_by": dict(est.absorbed_by),
        "warnings": list(est.warnings), "sigma_dof": float(est.sigma_dof),
        "visit_scatter": None if est.visit_scatter is None else
        {k: [float(x) for x in v] for k, v in est.visit_scatter.items()},
        "stated_used": list(est.stated_used), "scatter_warnings": list(est.scatter_warnings)})


def from_json(text: str) -> Estimate:
    """The estimate ``to_json`` wrote; ``ValueError`` when the text is not one."""
    try:
        d = json.loads(text)
        if d.get("format") != FORMAT:
            raise ValueError(f"format {d.get('format')!r}")
        layout = Layout(tuple(str(x) for x in d["links"]), int(d["n_balls"]),
                        bool(d["scale"]))
        est = Estimate(layout, [str(x) for x in d["ball_ids"]], _unarr(d["p"]),
                       _unarr(d["std"]), _unarr(d["cov"]), _unarr(d["residual_mm"]),
                       _unarr(d["distance_residual_um"]), float(d["residual_rms_um"]),
                       float(d["condition_number"]), _unarr(d["sigma_um"]),
                       bool(d["sigma_given"]), int(d["iterations"]), bool(d["converged"]),
                       str(d["status"]), [str(x) for x in d["unobservable"]],
                       {str(k): str(v) for k, v in d["absorbed_by"].items()},
                       [str(x) for x in d["warnings"]], float(d["sigma_dof"]),
                       visit_scatter=None if d["visit_scatter"] is None else
                       {str(k): (float(a), float(b), float(c))
                        for k, (a, b, c) in d["visit_scatter"].items()},
                       # absent from files written before the estimator carried them
                       stated_used=tuple(str(x) for x in d.get("stated_used", ())),
                       scatter_warnings=tuple(str(x) for x in d.get("scatter_warnings", ())))
    except (TypeError, KeyError, AttributeError, ValueError) as e:
        raise ValueError(f"not a stored estimate: {e!r}") from None
    n = layout.size
    if est.p.shape != (n,) or est.std.shape != (n,) or est.cov.shape != (n, n) \
            or math.isnan(est.sigma_dof):
        raise ValueError(f"not a stored estimate: sizes {est.p.shape}, {est.cov.shape} for "
                         f"{n} parameters")
    return est


def plan_to_json(plan: CompensationPlan) -> str:
    return json.dumps({
        "format": FORMAT, "changes": [[c.name, c.kind, c.delta, c.u_expanded, c.observable,
                                       c.note] for c in plan.changes],
        "links_identified": plan.links_identified, "links_compensable": plan.links_compensable,
        "links_residual": plan.links_residual,
        "distortion_um": [list(plan.distortion_before_um), list(plan.distortion_compensable_um),
                          list(plan.distortion_after_um)],
        # the displacements behind the figures (the worth rule's effects and subsets)
        "displacements": _displacements(plan)})


def _displacements(plan: CompensationPlan) -> dict[str, Any] | None:
    """The plan's displacements, each probed centre's row once: the plan's centres repeat
    every pose once per ball row (a 14-pose run: 224 rows, 56 distinct), so the distinct rows
    and the index that rebuilds the rest (exact) are stored — a quarter of the size."""
    if plan.link_disp_mm is None:
        return None
    names = list(plan.change_disp_mm)
    stacked = np.hstack([plan.link_disp_mm, *(plan.change_disp_mm[n] for n in names)])
    rows, index = np.unique(stacked, axis=0, return_inverse=True)
    return {"names": names, "rows": _arr(rows), "index": [int(i) for i in np.ravel(index)]}


def _from_displacements(d: dict[str, Any]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    full = _unarr(d["rows"])[np.asarray(d["index"], int)]
    names = [str(n) for n in d["names"]]
    if full.ndim != 2 or full.shape[1] != 3 * (len(names) + 1):
        raise ValueError(f"displacements of shape {full.shape} for {len(names)} changes")
    return full[:, :3], {n: full[:, 3 * (i + 1):3 * (i + 2)] for i, n in enumerate(names)}


def plan_from_json(text: str) -> CompensationPlan:
    """The plan ``plan_to_json`` wrote; ``ValueError`` when the text is not one."""
    try:
        d = json.loads(text)
        if d.get("format") != FORMAT:
            raise ValueError(f"format {d.get('format')!r}")
        changes = [ParamChange(str(n), str(k), float(v), float(u), bool(o), str(note))
                   for n, k, v, u, o, note in d["changes"]]
        links = [{str(k): float(v) for k, v in d[f"links_{w}"].items()}
                 for w in ("identified", "compensable", "residual")]
        dist = [(float(a), float(b)) for a, b in d["distortion_um"]]
        if d.get("displacements") is None:  # stored before the plan carried them
            raise ValueError("no displacements (stored before the worth rule)")
        return CompensationPlan(changes, *links, *dist, *_from_displacements(d["displacements"]))
    except (TypeError, KeyError, AttributeError) as e:
        raise ValueError(f"not a stored plan: {e!r}") from None


def save(store: Store, run_id: str, key: str, est: Estimate, plan: CompensationPlan) -> None:
    save_link_view(store, run_id, key, to_json(est), plan_to_json(plan), time.time())


def load(store: Store, run_id: str, key: str
         ) -> tuple[Estimate, CompensationPlan | None] | None:
    """The stored view of ``run_id`` for ``key``; None when there is none, it is for another
    key, or it cannot be read (it is then computed again); the plan None when only it cannot
    be read (stored before the plan carried its displacements: planned again from the stored
    estimate, which stays the run's own)."""
    row = link_view(store, run_id)
    if row is None or row[0] != key:
        return None
    try:
        est = from_json(row[1])
    except ValueError:
        return None
    try:
        return est, plan_from_json(row[2])
    except ValueError:
        return est, None


def stored_or_computed(setup: MachineSetup, store: Store, run_id: str, machine: Machine,
                       params: Sequence[ControllerParam], coverage_k: float
                       ) -> tuple[Estimate, CompensationPlan]:
    """The run's estimate against ``machine`` (the model at its start) and its plan: the
    stored ones, else computed now and stored (a journal opened read-only, or locked for
    longer than its busy timeout, only loses the storing)."""
    key = model_key(setup, machine, params, coverage_k)
    got = load(store, run_id, key)
    if got is not None and got[1] is not None:
        return got[0], got[1]
    c = estimation_centres(setup, run_centres(setup, store, run_id))
    if got is not None:  # the run's own estimate, planned again
        est = got[0]
        plan = plan_compensation(machine, setup.artefact, est, params, c.b_deg, c.c_deg,
                                 coverage_k=coverage_k)
    else:
        est, plan = compute(setup, c, run_id, machine, params, coverage_k)
    with contextlib.suppress(sqlite3.Error):  # computed again next time; same view
        save(store, run_id, key, est, plan)
    return est, plan


def at_run_end(setup: MachineSetup, store: Store, run_id: str, centre_rows: Sequence[tuple],
               machine: Machine, params: Sequence[ControllerParam], coverage_k: float,
               est: Estimate | None = None) -> None:
    """Compute and store the run's view as the run's analysis is made (its worker thread),
    from the centre rows the run is about to store: the HMI, the unattended path and `rumba
    compensate` then read it instead of identifying again. ``est``: the run's own estimate
    (the one its report shows: every visit, the fitted drift when selected); the plan is
    made from it, so the panel's links are the report's. Without it, or for
    another layout, the stored centres are identified again (first visit per pose)."""
    c = estimation_centres(setup, centres_of(setup, centre_rows, run_id))
    key = model_key(setup, machine, params, coverage_k)
    if est is not None and list(est.ball_ids) == list(setup.artefact.ids):
        plan = plan_compensation(machine, setup.artefact, est, params, c.b_deg, c.c_deg,
                                 coverage_k=coverage_k)
        save(store, run_id, key, est, plan)
        return
    save(store, run_id, key, *compute(setup, c, run_id, machine, params, coverage_k))
