"""The sim-to-real gap diagnosis (METHOD.md §6): locate, attribute, quantify, and say so honestly.

Pipeline: touches → sphere fits and the noise floor (``data``) → twin fitted on training data
(``twin``; plus any effects the user already models, ``Options.known``) → held-out split
(``split``: a separate log, leave-one-pose-out, time blocks for drift) → held-out gap of the
twin and where it lies (``locate``) → every library effect added and refitted, ranked by
held-out gap, greedy selection (``attribute``) → a drift verdict re-checked on time blocks →
verdict:

* ``none``: the held-out gap is at the floor (F test, level ``ALPHA``);
* ``absorbed``: at the floor, but the setup shows an effect the pattern cannot see — a fitted
  sphere radius off its nominal, uniformly over the balls: uniform pre-travel is taken up by
  the stylus setup (thesis §3.4);
* a family name: the selected effect removes at least half of the held-out excess;
* ``unexplained``: a significant gap no candidate explains, with its location;
* ``measurement_outlier``, ``ball_moved``, ``pole_defect``: one visit or one ball at fault
  (``outlier_visits``, ``step_ball``, ``visit_faults``), with what the rest reads.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from identification.effects import FAMILIES, Effect, library, model_name, sub_models
from identification.gap.attribute import (
    ALPHA,
    Candidate,
    contributions,
    explained,
    forward_select,
    gap_p_value,
    score,
    typical_size,
)
from identification.gap.centres_input import exact_floor
from identification.gap.data import Groups, TouchData, group_touches, repeat_floor_um
from identification.gap.floor import noise_floor_um, repeat_floor, whiteners
from identification.gap.known import add_known, known_report
from identification.gap.linear import Problem, columns, fit, held_out, projected
from identification.gap.locate import breakdowns
from identification.gap.outlier_visits import exclude_outliers
from identification.gap.scatter import confounded, link_report, model_visits, rescatter
from identification.gap.split import folds, time_check
from identification.gap.step_ball import step_report, step_verdict
from identification.gap.structure_floor import (
    after_selection,
    credit,
    floor_parts,
    seen_structure,
    unexplained_message,
)
from identification.gap.twin import effect_columns, fit_twin, touch_context
from identification.gap.visit_faults import pattern_explained, settle
from identification.gap.warmup import candidates as warmup_candidates
from identification.gap.warmup import model_of, tau_param
from identification.kinematics import Machine
from identification.model import Artefact, predict

DEFAULT_FOLDS = 0  # 0: the split's default (leave-one-pose-out, or split.TIME_BLOCKS blocks)
ABSORBED_SIGMAS = 5.0  # a mean radius deviation beyond this many standard errors is evidence
MIN_POSES = 4  # a twin with links needs several indexations; leave-one-out needs one more
SIGMA_REFINE = 0.9  # redo the diagnosis when the floor drops by more than 10 % without effects


@dataclass
class Options:
    families: Sequence[str] = FAMILIES
    n_folds: int = DEFAULT_FOLDS
    max_effects: int = 3
    # Effects the twin already models: (effect, params in effect units) — removed from the
    # observations as given — or (effect, None): added to the twin and fitted with the setup
    # and links on the training data of every fold. Neither is offered again as a candidate.
    known: Sequence[tuple[Effect, np.ndarray | None]] = ()
    split: str = "auto"  # internal split without a hold-out log: auto | pose | time (split.py)
    gravity_dir: Sequence[float] | None = None  # machine file ``gravity``; None: heuristic
    # stated centre repeatability (x, y, z µm): the floor where touches are exact (or absent)
    repeatability_um: Sequence[float] | None = None
    # Per-visit scatter (gap/scatter.py): index errors of the rotary axes and centre
    # scatter per ball visit as REML variance components; a stated rotary repeatability
    # (machine file ``rotary_repeatability_urad``, µrad 1σ per axis letter) is used as given.
    visit_scatter: bool = True
    rotary_repeatability_urad: dict[str, float] | None = None


def _merge(train: TouchData, holdout: TouchData | None) -> tuple[TouchData, np.ndarray]:
    if holdout is None:
        return train, np.zeros(len(train), bool)
    cat = {k: np.concatenate([getattr(train, k), getattr(holdout, k)])
           for k in TouchData.__dataclass_fields__}
    # The logs' pose numbers are their own: keep them apart (no repeats across logs).
    cat["repeat"] = np.concatenate([train.repeat, holdout.repeat + int(train.repeat.max()) + 1])
    cat["pose"] = np.concatenate([train.pose, holdout.pose + int(train.pose.max()) + 1])
    return TouchData(**cat), np.r_[np.zeros(len(train), bool), np.ones(len(holdout), bool)]


def diagnose(machine: Machine, artefact: Artefact, touches: TouchData, stylus_radius_mm: float,
             holdout: TouchData | None = None, options: Options | None = None) -> dict:
    """Run the whole diagnosis; returns the JSON-ready report (units µm, µrad, as labelled)."""
    opt = options or Options()
    all_data, all_hold = _merge(touches, holdout)
    all_groups = group_touches(all_data, artefact, stylus_radius_mm)

    def run(keep: frozenset[int] = frozenset(), drop: frozenset[int] = frozenset()):
        data, hold_rows, groups, faulty = exclude_outliers(  # a chip …: out of floor and twin
            machine, artefact, all_data, all_hold, all_groups, stylus_radius_mm,
            holdout and touches, keep, drop)
        groups, note = exact_floor(groups, opt.repeatability_um)  # never a zero form residual
        return diagnose_groups(machine, artefact, data, groups,
                               hold_rows[groups.touch_index[:, 0]], opt, note), faulty

    return settle(run, lambda rep, k: pattern_explained(  # a chip, or a pattern across visits?
        machine, artefact, all_data, all_groups, stylus_radius_mm, rep, k, opt.gravity_dir),
        lambda k: all_groups.centres.xyz_mm[k])


def diagnose_groups(machine: Machine, artefact: Artefact, data: TouchData, groups: Groups,
                    is_ho: np.ndarray, options: Options | None = None, note: str = "") -> dict:
    """The diagnosis of ready groups (touches: ``diagnose``; centres: ``gap.centres_input``);
    ``note`` says where a floor not from the form residuals came from."""
    opt = options or Options()
    unknown = sorted(set(opt.families) - set(FAMILIES))
    if unknown:
        raise ValueError(f"unknown effect families {unknown}; expected some of {FAMILIES}")
    n_train_poses = len(np.unique(groups.centres.pose[~is_ho]))
    if n_train_poses < MIN_POSES:
        raise ValueError(f"{n_train_poses} complete poses to fit the twin on; the diagnosis "
                         f"needs at least {MIN_POSES}")
    floored, rnote = repeat_floor(groups)
    rep, refined = _analyse(machine, artefact, data, floored, is_ho, opt)
    if groups.channels < 4:
        rep["noise"]["source"] = note
        refined = None  # the refinement re-estimates a form-residual floor: there is none
    rep["noise"]["source"] += rnote
    if refined is not None and refined[0] < SIGMA_REFINE * groups.sigma_touch_um:
        # The form residuals that gave the floor also carried the selected effects' sphere
        # distortion (e.g. the local slope of a straightness): estimate it again without them
        # and redo the diagnosis with the cleaner floor (repeats, if any, still bound it).
        floored, note = repeat_floor(groups.with_sigma(*refined))
        rep, _ = _analyse(machine, artefact, data, floored, is_ho, opt)
        rep["noise"]["source"] += (f"; re-estimated without the selected effects (first pass "
                                   f"{groups.sigma_touch_um:.3f} µm){note}")
    seen = seen_structure(rep.get("structure"))  # later passes keep the first one's rule
    return step_verdict(rescatter(rep, lambda w, g: _analyse(machine, artefact, data, floored,
                                                             is_ho, opt, w, g, seen)[0],
                                  machine, artefact.ids, opt.gravity_dir))


def _analyse(machine: Machine, artefact: Artefact, data: TouchData, groups: Groups,
             is_ho: np.ndarray, opt: Options, scatter_with: Sequence[Effect] = (),
             lr_gate: frozenset[str] = frozenset(), seen: str = ""
             ) -> tuple[dict, tuple[float, int] | None]:
    whiten = whiteners(groups)
    train = ~is_ho
    twin = fit_twin(machine, artefact, groups.centres.subset(train), whiten[train, :3, :3])
    pred = twin.predicted_um(groups.centres, groups)
    base_pred_mm, _ = predict(machine, artefact, twin.layout, twin.p, groups.centres)
    twin_cols, ball_jac = twin.base_columns(groups.centres, groups, base_pred_mm)
    problem = Problem(groups.obs_um() - pred, twin_cols, whiten, np.zeros(len(groups), int))
    problem.fold, split, split_mode = folds(groups, is_ho, opt.split, opt.n_folds)
    ctx = touch_context(data, twin)
    fixed, fitted = add_known(problem, opt.known, twin, groups, ctx, ball_jac, base_pred_mm)
    base = problem.base  # the twin: setup + links (+ the known effects fitted with them)
    known = {e.label for e, _ in opt.known}

    rep_floor = repeat_floor_um(groups)
    lib = [(e, effect_columns(e, twin, groups, ctx, ball_jac, base_pred_mm))
           for e in [*library(machine, artefact.ids, gravity_dir=opt.gravity_dir),
                     *sub_models(machine)] if e.family in opt.families and e.label not in known]
    vs, step, n_step, twin_structure = model_visits(
        machine, artefact, problem, groups, twin, ctx, ball_jac, base_pred_mm,
        opt.visit_scatter, opt.rotary_repeatability_urad, scatter_with, [c for _, c in lib])
    base = problem.base  # with a moved ball's step (gap/step_ball.py)
    # Structure along an axis is tested before the components are credited to the floor: a
    # function of the axis position is not visit scatter (gap/structure_floor.py)
    vs, struct = credit(problem, groups, vs, base, vs.extra if vs else [],
                        sorted(vs.labels) if vs else [], opt.rotary_repeatability_urad,
                        twin_structure, seen)
    if vs is not None:  # the floor's dof now include the estimated components'
        groups = replace(groups, sigma_dof=max(int(vs.dof), 1))
    noise_floor = vs.floor_um if vs is not None else noise_floor_um(groups)
    base_full = fit(problem, base)
    base_ho = held_out(problem, base)
    cells = breakdowns(groups, base_ho, artefact.ids)
    sig_cells = sorted((c for c in cells if c.significant), key=lambda c: -c.ratio)
    # The gap is significant if the whole held-out set or any breakdown cell (family-wise
    # level ALPHA, Bonferroni) stands above the floor: a gap confined to a few cells would be
    # diluted in the global test.
    p_gap = min(gap_p_value(base_ho, groups.sigma_dof), min((c.p_value * len(cells)
                                                          for c in cells), default=1.0))

    cands: list[Candidate] = []
    invisible: list[dict] = []
    for eff, cols in lib:
        _, r, basis = projected(problem, base, cols, typical_size(eff))
        if r == 0:
            invisible.append({"effect": eff.family, "axis": eff.axis,
                              "reason": "no visible effect of realistic size on this "
                                        "probing pattern (absorbed by the setup and link "
                                        "errors, or not excited)"})
        cands.append(Candidate(eff, np.einsum("gom,mr->gor", cols, basis), r, basis))
    cands += warmup_candidates(  # the exponential warm-up, τ profiled
        machine, problem, base,
        lambda e: effect_columns(e, twin, groups, ctx, ball_jac, base_pred_mm), typical_size,
        opt.families, known)
    visible = [c for c in cands if c.visible_dof > 0]
    score(problem, visible, [], base_full)
    suspect = confounded(vs, problem, groups, visible, ALPHA)  # inflating the components?
    n_try = max(len(visible), 1)
    for c in visible:
        c.significant = bool(c.p_value < ALPHA / n_try and c.delta_bic < 0
                             and c.ho.ss_w < base_ho.ss_w)
    contributions(problem, visible)
    visible.sort(key=lambda c: (c.ho.ss_w, c.effect.n_params))
    selected, final_ho = [], base_ho
    # Only a significant gap is attributed — or an effect a likelihood ratio with the scatter
    # components profiled found (gap/scatter.confounded): the held-out test is weak when the
    # floor rests on few visits (its Satterthwaite dof).
    if p_gap < ALPHA or struct.found or any(c.effect.label in lr_gate for c in visible):
        selected, final_ho, _ = forward_select(problem, visible, base_full, base_ho,
                                               opt.max_effects)

    n_base = base.shape[2]
    scale = noise_floor**2 * base_ho.expected_ss / base_ho.n_obs
    holdout_floor = float(np.sqrt(scale))
    cand_out = []
    for c in visible:
        cand_out.append({
            "effect": c.effect.family, "axis": c.effect.axis,
            "params": c.params(n_base) | tau_param(c.effect), **model_of(c.effect),
            **model_name(c.effect),
            "holdout_rms_um": round(c.ho.rms_um, 4), "holdout_max_um": round(c.ho.max_um, 4),
            "explained_fraction": round(explained(base_ho, c.ho), 4),
            "significant": c.significant, "p_value": float(f"{c.p_value:.3g}"),
            "delta_bic": round(c.delta_bic, 2), "n_params": c.effect.n_params,
            "visible_dof": c.visible_dof, "indistinguishable_from": c.alike,
        })

    frac = explained(base_ho, final_ho)
    tcheck = time_check(problem, groups, is_ho, selected, split_mode, frac)
    full_cols = {e.label + str(e.param_names): cols for e, cols in lib}
    after_selection(struct, problem, groups, vs, base,
                    [full_cols.get(c.label + str(c.effect.param_names), c.cols)
                     for c in selected], [c.label for c in selected],
                    gap_p_value(final_ho, groups.sigma_dof))
    refined = None
    if selected or fitted:
        # The form residuals that set the floor also carry the fitted effects' sphere
        # distortion: the floor is estimated again without it (see ``diagnose``).
        full = fit(problem, columns(problem, [c.cols for c in selected]))
        e_form = full.e_um[:, 3]
        dof = max(len(e_form) - 1 - sum(c.visible_dof for c in (*selected, *fitted)), 1)
        refined = (float(max(np.sqrt(np.sum(e_form**2) / dof), 1e-3)), dof)
    radius_dev = groups.radius_dev_um
    se = float(np.std(radius_dev, ddof=1) / np.sqrt(len(radius_dev))) if len(radius_dev) > 1 \
        else float("inf")
    mean_dev = float(np.mean(radius_dev))
    radius_evidence = abs(mean_dev) > max(ABSORBED_SIGMAS * se, noise_floor)
    absorbed = []
    if radius_evidence:
        absorbed.append({"effect": "probe_pretravel", "axis": None,
                         "what": "part identical for every ball and direction (or a stylus "
                                 "radius error): taken up by the fitted radius",
                         "value_um": round(-mean_dev, 3), "std_um": round(se, 3)})
    if p_gap >= ALPHA and not selected and not struct.found:
        if radius_evidence:
            effect, axis = "absorbed", None
            message = (f"held-out gap at the floor, but every ball's fitted radius is off its "
                       f"nominal by {mean_dev:+.2f} µm: a probe pre-travel identical for every "
                       "ball (or a stylus radius error), taken up by the stylus setup "
                       "(thesis §3.4); it does not bias the centres")
        else:
            effect, axis = "none", None
            message = "held-out gap consistent with the probing noise floor"
    elif selected and frac >= 0.5 and (tcheck is None or tcheck["confirmed"]) \
            and not struct.unexplained:
        effect, axis = selected[0].effect.family, selected[0].effect.axis
        names = ", ".join(c.label for c in selected)
        message = f"selected {names}: explains {100 * frac:.0f} % of the held-out excess"
        if fitted or fixed:
            message += " left by the known effects"
    else:
        effect, axis = "unexplained", None
        where = ", ".join(f"{c.by} {c.key}" for c in sig_cells[:3]) or "no single breakdown"
        message = f"significant gap that no library effect explains; largest at {where}"
        if struct.found:
            message = unexplained_message(struct, selected, frac)
        elif tcheck is not None:
            names = ", ".join(c.label for c in selected)
            message += (f"; {names} explains {100 * frac:.0f} % leaving poses out but only "
                        f"{100 * tcheck['explained_fraction']:.0f} % of held-out stretches "
                        "of the run (time blocks): its time course does not extrapolate — a "
                        "drift of another shape (a thermal cycle, a step)?")
        elif rep_floor is None and vs is None:
            message += ("; without repeats the floor knows only the trigger noise — a "
                        "non-repeatable centre scatter (indexing, clamping) looks like this: "
                        "run the plan with repeats ≥ 2 to measure it")

    attributed = effect not in ("none", "absorbed", "unexplained")
    after_ho = final_ho if attributed else base_ho
    location = [c.as_dict() for c in sig_cells]
    if not location and p_gap < ALPHA:
        location = [c.as_dict() for c in sorted(cells, key=lambda c: -c.ratio)[:3]]
    return {
        "noise_floor_um": round(noise_floor, 4),
        "noise": {"source": "sphere-fit form residuals", "sigma_touch_um":
                  round(groups.sigma_touch_um, 4), "dof": groups.sigma_dof,
                  "repeat_floor_um": round(rep_floor[0], 4) if rep_floor else None,
                  "holdout_floor_um": round(holdout_floor, 4),
                  "radius_dev_mean_um": round(mean_dev, 4),
                  "parts": floor_parts(vs, noise_floor)},
        "split": split,
        "split_mode": split_mode,
        "time_check": tcheck,
        "known": known_report(fixed, fitted, base_full, twin_cols.shape[2]),
        "twin": {"links": list(twin.layout.links), "unobservable": twin.dropped,
                 "n_params": twin_cols.shape[2], "n_known_params": n_base - twin_cols.shape[2],
                 "groups_train": int(train.sum()),
                 "groups_holdout": int(is_ho.sum()) if is_ho.any() else len(groups)},
        "baseline": {"train_rms_um": round(float(np.sqrt(np.mean(
                         base_full.e_um[:, :groups.channels] ** 2))), 4),
                     "holdout_rms_um": round(base_ho.rms_um, 4),
                     "holdout_max_um": round(base_ho.max_um, 4),
                     "gap_ratio": round(base_ho.ratio, 3), "p_value": float(f"{p_gap:.3g}")},
        "candidates": cand_out,
        "invisible": invisible,
        "absorbed": absorbed,
        "scatter": vs.finding() | {"confounded_with": suspect} if vs is not None else None,
        "ball_step": step_report(step, problem, artefact.ids, n_step) if step else None,
        "structure": struct.as_dict(),
        "links": link_report(problem, twin, selected, n_base),
        "dropped_groups": groups.dropped,
        "verdict": {"effect": effect, "axis": axis,
                    "holdout_rms_before_um": round(base_ho.rms_um, 4),
                    "holdout_rms_after_um": round(after_ho.rms_um, 4),
                    # the floor the model with the selected effects can reach on held-out
                    # data: its own fitted parameters' prediction variance included
                    "holdout_floor_after_um": round(float(np.sqrt(
                        noise_floor**2 * after_ho.expected_ss / after_ho.n_obs)), 4),
                    "holdout_max_before_um": round(base_ho.max_um, 4),
                    "holdout_max_after_um": round(after_ho.max_um, 4),
                    "selected": [{"effect": c.effect.family, "axis": c.effect.axis,
                                  **model_of(c.effect), **model_name(c.effect),
                                  "params": c.params(n_base) | tau_param(c.effect)}
                                 for c in selected],
                    "explained_fraction": round(frac, 4), "message": message},
        "location": location,
        "breakdowns": [c.as_dict() | {"significant": c.significant} for c in cells],
        "residuals": _series(groups, base_ho, final_ho, artefact.ids),
    }, refined


def _series(groups: Groups, before, after, ids: list[str]) -> dict:
    """Held-out residuals per ball-pose before and after the selected effects (for plots)."""
    c, g = groups.centres, before.index
    return {"ball": [ids[int(b)] for b in c.ball[g]], "pose": c.pose[g].tolist(),
            "b_deg": c.b_deg[g].round(4).tolist(), "c_deg": c.c_deg[g].round(4).tolist(),
            "t_s": c.t_s[g].round(2).tolist(), "xyz_mm": c.xyz_mm[g].round(3).tolist(),
            "before_um": before.e_um.round(4).tolist(), "after_um": after.e_um.round(4).tolist(),
            "columns": ["x", "y", "z", "form"]}
