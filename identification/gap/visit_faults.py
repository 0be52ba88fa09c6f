"""One visit's fault or a pattern across visits: settle the outlier test against the
diagnosis.

A chip is one ball at one visit; a systematic effect spans visits. The outlier test
(``identification.outliers``) judges a visit against the twin and the run's robust scales, which
know nothing of the effect the diagnosis is looking for: a straightness of X at 5 × the
scatter-aware floor bends the visits far along X (centre stage) and shears their probed spheres
(sphere stage: its local slope), and the worst two were named pole chips. So an outlier is
confirmed only when it still stands out once the effects the rest of the run selects are
removed from every visit — their fitted contribution to the centre and to the form residual,
touch by touch (``pattern_explained``); one that the pattern predicts goes back into the
diagnosis and is named under ``explained_visits``.

The other way round, a pole chip smaller than the run can name (``chip_floor``: the pole only
moves the centre, which the per-visit scatter blurs; the five touches hold no second look at it)
leaves a gap at that visit that no library effect explains. When the rest reads ``unexplained``,
the visit most displaced along its pole normal (the screen's largest one-sided centre z, the chip
side) is left out and the run diagnosed again: if the rest is then explained, the verdict is
``pole_defect`` — the gap is consistent with a pole defect of that size, below the detectable
one, on that ball at that pose — instead of ``unexplained``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from identification.effects import Effect, library, sub_models
from identification.gap.data import Groups, TouchData
from identification.gap.outlier_visits import outlier_verdict
from identification.kinematics import Machine
from identification.model import Artefact, predict
from identification.outliers import find_outliers

POLE_VERDICT = "pole_defect"
Run = Callable[..., tuple[dict, dict]]  # (keep=…, drop=…) → (report, outlier parts)


def _effect(machine: Machine, ids: list[str], sel: dict, gravity_dir) -> Effect | None:
    """The library effect (or single-harmonic variant) a verdict's ``selected`` entry names,
    matched by family, axis and parameter names; None for one not in it (a profiled warm-up)."""
    names = set(sel.get("params", {}))
    for e in [*library(machine, ids, gravity_dir=gravity_dir), *sub_models(machine)]:
        if (e.family, e.axis) == (sel["effect"], sel["axis"]) and set(e.param_names) == names:
            return e
    return None


def pattern_explained(machine: Machine, artefact: Artefact, data: TouchData, groups: Groups,
                      stylus_radius_mm: float, rep: dict, candidates: list[int],
                      gravity_dir=None) -> list[int]:
    """Which of the ``candidates`` (the test's outliers, indices into ``groups``) are no
    outliers once the selected effects' fitted contribution is removed from every visit."""
    from identification.gap.twin import effect_columns, fit_twin, touch_context

    sel = rep["verdict"].get("selected") or []
    effects = [(_effect(machine, artefact.ids, s, gravity_dir), s) for s in sel]
    if not sel or any(e is None for e, _ in effects):
        return []
    c = groups.centres
    clean = np.ones(len(groups), bool)
    clean[candidates] = False
    twin = fit_twin(machine, artefact, c.subset(clean))
    q, _ = predict(machine, artefact, twin.layout, twin.p, c)
    _, ball_jac = twin.base_columns(c, groups, q)
    ctx = touch_context(data, twin)
    contrib_um = np.zeros((len(groups), 4))  # centre x y z and form, as the diagnosis sees it
    for e, s in effects:
        theta = np.array([s["params"][n]["value"] for n in e.param_names])
        contrib_um += effect_columns(e, twin, groups, ctx, ball_jac, q) @ theta
    # Undo it touch by touch: the centre shift moves all five; the form part (an effect's
    # sphere distortion, e.g. the local slope of a straightness) moves each along its normal
    # by its share of the sphere-free residual direction.
    radial_um = -contrib_um[:, 3:4] * groups.form_dir
    pts = data.xyz_mm[groups.touch_index] + 1e-3 * (
        radial_um[:, :, None] * groups.normal - contrib_um[:, None, :3])
    r_nom = np.array([artefact.balls[b].diameter_mm / 2 for b in c.ball]) + stylus_radius_mm
    scr = find_outliers(machine, artefact, c, pts, r_nom, groups.repeat)
    still = {o.index for o in scr.outliers}
    return [k for k in candidates if k not in still]


def settle(run: Run, explained: Callable[[dict, list[int]], list[int]],
           positions: Callable[[list[int]], np.ndarray] | None = None) -> dict:
    """The diagnosis with the outlier test settled both ways (module docstring). ``run``
    diagnoses the run with given group indices kept in (``keep``) or left out (``drop``)
    beyond the test's own outliers; ``explained``: ``pattern_explained`` bound to the run;
    ``positions``: the groups' centres (controller mm), for ``along_structure``."""
    rep, parts = run()
    named = [o["index"] for o in parts["outliers"]]
    keep: frozenset[int] = frozenset()
    # a rest left with structure along an axis: are the named visits part of it? (before
    # asking whether a library effect that leaves the structure predicts them)
    structured = bool((rep.get("structure") or {}).get("found")) \
        and rep["verdict"]["effect"] == "unexplained"
    if named and positions is not None and structured:
        rep, parts, keep = along_structure(run, rep, parts, named, positions)
    if named and not keep and rep["verdict"].get("selected"):
        back = explained(rep, named)
        if back:
            keep = frozenset(back)
            named = [o for o in parts["outliers"] if o["index"] in keep]
            rep, parts = run(keep=keep)
            label = _labels(rep)
            parts["explained_visits"] = [
                {k: v for k, v in o.items() if k != "index"}
                | {"explained_by": label,
                   "note": "its centre departs as the effect predicts: a pattern across "
                           "visits, not a chip on one"} for o in named]
    if named and not keep and positions is not None and not structured:
        rep, parts, keep = along_structure(run, rep, parts, named, positions)
    suspect = parts["outlier_test"].get("pole_suspect")
    if rep["verdict"]["effect"] == "unexplained" and suspect is not None:
        rest, rest_parts = run(keep=keep, drop=frozenset({suspect["index"]}))
        if rest["verdict"]["effect"] != "unexplained" and not (
                {o["index"] for o in rest_parts["outliers"]}
                - {o["index"] for o in parts["outliers"]}):
            return _clean(pole_verdict(outlier_verdict(rest, rest_parts), suspect))
    return _clean(outlier_verdict(creep_note(rep), parts))


TOUCH_REACH_MM = 16.0  # a ball's touches reach this far from its centre (Ø 25.4 + stylus)


def along_structure(run: Run, rep: dict, parts: dict, named: list[int],
                    positions: Callable[[list[int]], np.ndarray]
                    ) -> tuple[dict, dict, frozenset[int]]:
    """A local defect of a guideway deforms the probed sphere of every ball visit that
    straddles it: the sphere stage names those visits chips, and with them left out the
    rest may show nothing. So the run is diagnosed again with them kept in; they go back
    into the diagnosis when it then finds structure along an axis that reaches them (a
    local shape: most of them within one width and a ball's touch reach of its centre) and
    either more than one visit was named — a chip is one visit — or the rest already showed
    the structure."""
    rest_found = bool((rep.get("structure") or {}).get("found"))
    visits = {(o["log"], o["repeat"], o["pose"]) for o in parts["outliers"]}
    if len(visits) < 2 and not rest_found:
        return rep, parts, frozenset()
    keep = frozenset(named)
    rep_k, parts_k = run(keep=keep)
    st = rep_k.get("structure") or {}
    loc = st.get("located") or {}
    if not st.get("found") or not loc:
        return rep, parts, frozenset()
    q = positions(named)[:, "XYZ".index(loc["axis"])]
    # a local shape fitted with its worst-deformed visits in is narrower than the bump (their
    # spheres bend most where it is steepest, at its flanks): one width either side
    if loc["shape"] == "local" and np.mean(
            np.abs(q - loc["centre_mm"]) <= loc["width_mm"] + TOUCH_REACH_MM) < 0.5:
        return rep, parts, frozenset()
    parts_k["explained_visits"] = [
        {k: v for k, v in o.items() if k != "index"}
        | {"explained_by": f"structure along {loc['axis']}",
           "note": f"its sphere departs where the structure along {loc['axis']} lies: a "
                   "pattern along the axis, not a chip on one visit"}
        for o in parts["outliers"]]
    return rep_k, parts_k, keep


def creep_note(rep: dict) -> dict:
    """A creeping ball (``artefact_instability``, a ramp over the run, not a step) named with
    its rate, direction and the distance over the run; and the effect it cannot be told from
    on this run (a warm-up drift of one axis moves every ball alike, but with few balls and
    poses the two may be collinear: the candidates' ``indistinguishable_from``)."""
    v = rep["verdict"]
    if v["effect"] != "artefact_instability" or not v["axis"]:
        return rep
    sel = next(s for s in v["selected"] if s["effect"] == "artefact_instability")
    rate = np.array([sel["params"][f"creep_{v['axis']}_{a}"]["value"] for a in "xyz"])
    t = np.asarray(rep["residuals"]["t_s"], float)
    span_h = float(np.ptp(t)) / 3600.0 if t.size else 0.0
    speed = float(np.linalg.norm(rate))
    alike = next((c["indistinguishable_from"] for c in rep["candidates"]
                  if (c["effect"], c["axis"]) == ("artefact_instability", v["axis"])), [])
    rep["ball_creep"] = {"ball": v["axis"], "rate_um_per_h": round(speed, 3),
                         "vector_um_per_h": [round(float(x), 3) for x in rate],
                         "over_run_um": round(speed * span_h, 3),
                         "run_min": round(60 * span_h, 1), "indistinguishable_from": alike}
    v["message"] += (f"; ball {v['axis']} creeping at {speed:.1f} µm/h ("
                     + "/".join(f"{x:+.1f}" for x in rate) + " x/y/z, workpiece frame): "
                     f"{speed * span_h:.1f} µm over the run's {60 * span_h:.0f} min — loose "
                     "in its holder?"
                     + (f" On this run it cannot be told from {' or '.join(alike)}."
                        if alike else ""))
    return rep


def _labels(rep: dict) -> str:
    return ", ".join(s["effect"] + (f":{s['axis']}" if s["axis"] else "")
                     for s in rep["verdict"].get("selected") or [])


def _clean(rep: dict) -> dict:
    """Group indices are internal (they change with every exclusion)."""
    for o in rep.get("outliers", ()):
        o.pop("index", None)
    ps = (rep.get("outlier_test") or {}).get("pole_suspect")
    if ps:
        ps.pop("index", None)
    return rep


def pole_verdict(rep: dict[str, Any], suspect: dict[str, Any]) -> dict[str, Any]:
    """Verdict ``pole_defect``: the suspect visit left out explains the gap; what the rest reads
    is kept under ``verdict.without_pole_visit``."""
    v = rep["verdict"]
    pole = (rep["outlier_test"].get("min_chip_um") or {}).get("pole")
    axis = f":{v['axis']}" if v["axis"] else ""
    rep_at = f" repeat {suspect['repeat']}" if suspect["repeat"] else ""
    log = " of the hold-out log" if suspect["log"] == "holdout" else ""
    below = f", below the {pole:.1f} µm this run's outlier test names on the pole" if pole \
        else ""
    rep["pole_defect"] = {k: val for k, val in suspect.items() if k != "index"}
    rep["verdict"] = {**v, "effect": POLE_VERDICT, "axis": None,
                      "without_pole_visit": {"effect": v["effect"], "axis": v["axis"],
                                             "message": v["message"]},
                      "message": (f"the gap is consistent with a pole defect of ≈ "
                                  f"{suspect['size_um']:.1f} µm on ball {suspect['ball']} at "
                                  f"pose {suspect['pose']}{rep_at}{log} (touch 5, robust z "
                                  f"{suspect['z']:.1f}{below}): a chip, dirt or coolant the "
                                  f"five touches cannot tell from the ball's height; left out, "
                                  f"the rest reads {v['effect']}{axis} ({v['message']}) — "
                                  f"re-probe that ball to confirm")}
    return rep
