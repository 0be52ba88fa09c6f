"""The scatter-aware floor of the gap diagnosis: per-visit index and centre scatter.

``identification.visit_scatter`` estimates the components by REML on the twin's residuals
(fixed effects: setup, links, the known and the already selected effects); here they become
the diagnosis' whitening (generalised least squares per visit), its floor and the finding the
report states ("C indexing repeatability ≈ 9 µrad (1σ), estimated from …"). A stated rotary
repeatability (machine file ``rotary_repeatability_urad``) is used as given for its axis.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from identification.effects import Effect, model_name
from identification.gap.data import Groups, visit_ids
from identification.gap.linear import Problem, live
from identification.gap.step_ball import Step, find_step
from identification.gap.structure import AXES, Structure, test_structure
from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict
from identification.tails import chi2_sf
from identification.visit_scatter import (
    LR_ALPHA,
    ScatterFit,
    VisitBlocks,
    arrange,
    effective_dof,
    estimate_components,
    whiteners,
)

H_DEG = 1e-3  # finite-difference step of the index columns (the chain is smooth in the angle)
START_URAD = 5.0
START_UM = 0.2
MAX_PASSES = 3  # diagnoses redone with the components re-estimated (``rescatter``)
SCREEN_P = 0.01  # F-test level (sphere-fit whitening) to be profiled by ``confounded``


@dataclass
class VisitScatter:
    """What the run says about its per-visit scatter, and the blocks that carry it."""

    fit: ScatterFit
    blocks: VisitBlocks
    axes: tuple[str, ...]  # rotary axis letters of the index components
    floor_um: float  # RMS noise floor per live observation with the components
    dof: float  # effective dof of that floor (Welch–Satterthwaite)
    source: str
    z: np.ndarray  # (G, 4, q) the index columns per group
    extra: list  # columns of the effects estimated with the components as fixed effects
    labels: frozenset  # their labels
    # Why the centre components are not credited (structure along an axis: they would take
    # it up, gap/structure_floor.py), "" when they are estimated
    withheld: str = ""
    n_live: float = 0.0  # live observations the floor is an RMS over

    def parts_um(self) -> dict[str, float]:
        """The floor's parts, RMS per live observation (their squares add up to the floor's):
        the trigger noise of the touches (the sphere fits' covariance and form residual),
        the rigid index scatter of the rotary axes, and the centre scatter per ball visit."""
        b, th, q = self.blocks, self.fit.sigma, len(self.axes)
        n = max(self.n_live, 1.0)
        index = sum(float(np.sum(b.z[:, :, i] ** 2)) * th[i] ** 2 for i in range(q))
        centre = sum(float(np.sum(b.centre[:, :, a])) * th[q + a] ** 2 for a in range(3))
        trigger = max(self.floor_um**2 * n - index - centre, 0.0)
        return {"trigger_um": float(np.sqrt(trigger / n)), "index_um": float(np.sqrt(index / n)),
                "ball_visit_um": float(np.sqrt(centre / n))}

    def finding(self) -> dict:
        """The report's ``scatter`` part: each component with u, its test and a sentence."""
        out = []
        for i, name in enumerate(self.fit.names):
            v, u, p = self.fit.sigma[i], self.fit.std[i], self.fit.p_value[i]
            unit = "urad" if name.startswith("index") else "um"
            ci = self.fit.ci95[i] if self.fit.ci95 is not None else (np.nan, np.nan)
            held = self.is_withheld(i)
            out.append({"component": name, "sigma": round(float(v), 3),
                        "std": None if not np.isfinite(u) else round(float(u), 3),
                        # the 95 % likelihood interval (σ̂ is skewed with a dozen visits)
                        "ci95": None if np.isnan(ci[0]) else [round(float(ci[0]), 3),
                                                              round(float(ci[1]), 3)],
                        "unit": unit, "stated": bool(self.fit.fixed[i]) and not held,
                        "withheld": held,
                        "p_value": None if not np.isfinite(p) else float(f"{p:.3g}"),
                        "detected": bool((self.fit.fixed[i] and not held)
                                         or (np.isfinite(p) and p < LR_ALPHA))})
        return {"components": out, "floor_um": round(self.floor_um, 4),
                "withheld": self.withheld or None,
                "dof": round(self.dof, 1), "visits": self.fit.n_visits, "source": self.source,
                "message": self.message()}

    def is_withheld(self, i: int) -> bool:
        return bool(self.withheld) and i >= len(self.axes)

    def message(self) -> str:
        parts = []
        for i, name in enumerate(self.fit.names):
            v, u = self.fit.sigma[i], self.fit.std[i]
            stated = self.fit.fixed[i]
            if self.is_withheld(i):
                continue
            if not stated and not (np.isfinite(self.fit.p_value[i])
                                   and self.fit.p_value[i] < LR_ALPHA):
                continue
            unit = "µrad" if name.startswith("index") else "µm"
            what = (f"{name[6:]} indexing repeatability" if name.startswith("index")
                    else f"centre scatter {name[-1]} per ball visit")
            how = "stated in the machine file" if stated else (
                f"± {u:.2g}" if np.isfinite(u) else "estimated")
            ci = self.fit.ci95[i] if self.fit.ci95 is not None else (np.nan, np.nan)
            if not stated and np.isfinite(ci[0]):
                how += f"; 95 % {ci[0]:.3g}-{ci[1]:.3g}"
            parts.append(f"{what} ≈ {v:.3g} {unit} (1σ, {how})")
        held = (f"; centre scatter per ball visit not credited to the floor: "
                f"{self.withheld}") if self.withheld else ""
        if not parts:
            return ("no per-visit scatter beyond the trigger noise detected "
                    f"({self.source}){held}")
        out = "; ".join(parts) + f" — estimated from {self.source}"
        q = len(self.axes)
        if any(not self.fit.fixed[i] and np.isfinite(self.fit.p_value[i])
               and self.fit.p_value[i] < LR_ALPHA for i in range(q)):
            # Which quantity it states: σ̂ follows the run's own index errors (bench_scatter:
            # within 30 % of their RMS in ~all null runs), and that RMS of n draws spreads
            # 1/√(2n) around the machine's σ, which only the 95 % interval is about.
            n = self.fit.n_visits
            out += (f" (an indexing repeatability from {n} indexations follows this run's own "
                    f"index errors, whose RMS alone spreads ± {100 / np.sqrt(2 * n):.0f} % "
                    "around the axis' σ: the 95 % interval is the one for σ)")
        return out + held


def index_columns(machine: Machine, artefact: Artefact, layout: Layout, p: np.ndarray,
                  centres: Centres, groups: Groups) -> tuple[np.ndarray, tuple[str, ...]]:
    """(G, 4, q) change of the observations (µm) per µrad of index error of each rotary axis
    (the true axis at command + δ: the whole workpiece side turns, the sphere keeps its form),
    and the axis letters."""
    q0, _ = predict(machine, artefact, layout, p, centres)
    axes = tuple(machine.rotary_axes)
    out = np.zeros((len(groups), 4, len(axes)))
    h_urad = np.deg2rad(H_DEG) * 1e6
    for k in range(len(axes)):
        moved = Centres(centres.pose, centres.ball, centres.b_deg + (H_DEG if k == 0 else 0.0),
                        centres.c_deg + (H_DEG if k == 1 else 0.0), centres.xyz_mm,
                        centres.t_s)
        q1, _ = predict(machine, artefact, layout, p, moved)
        out[:, :3, k] = (q1 - q0) * 1e3 / h_urad
    return out, axes


def estimate_scatter(problem: Problem, groups: Groups, z: np.ndarray, axes: tuple[str, ...],
                     extra: list[np.ndarray] | None = None,
                     stated_urad: Mapping[str, float] | None = None,
                     withheld: str = "") -> VisitScatter:
    """REML components on the problem's residuals with the twin (and ``extra``) columns as
    fixed effects; the per-group covariance of the sphere fits is the known part. With
    ``withheld`` (the reason) the centre components are held at zero, not estimated."""
    cov = np.zeros((len(groups), 4, 4))
    cov[:, :3, :3] = groups.centre_cov_um2
    cov[:, 3, 3] = groups.sigma_touch_um**2
    x = np.concatenate([problem.base, *(extra or [])], axis=2)
    blocks = arrange(problem.y_um, x, cov, z, visit_ids(groups), live(problem))
    names = tuple([f"index {a}" for a in axes] + [f"centre {a}" for a in "xyz"])
    stated = {i: float(stated_urad[a]) for i, a in enumerate(axes)
              if stated_urad and a in stated_urad}
    if withheld:
        stated |= {len(axes) + k: 0.0 for k in range(3)}
    start = [START_URAD] * len(axes) + [START_UM] * 3
    fit = estimate_components(blocks, names, start, stated)
    theta = fit.sigma
    n_live = float(np.sum(live(problem)))
    from identification.visit_scatter import covariance

    var = np.trace(covariance(blocks, theta), axis1=1, axis2=2).sum() - \
        (blocks.y.shape[1] * len(blocks.groups) - n_live)  # pads/dead channels carry unit var
    floor = float(np.sqrt(var / n_live))
    dof = effective_dof(blocks, theta, fit, groups.sigma_dof)
    rep = groups.repeat
    revisits = len(np.unique(visit_ids(groups))) - len(np.unique(groups.centres.pose))
    source = (f"{fit.n_visits} visits"
              + (f" ({revisits} revisits of a pose)" if revisits else
                 ", the pattern across the balls of each visit (no repeats)")
              + (f", {len(np.unique(rep))} passes" if len(np.unique(rep)) > 1 else ""))
    return VisitScatter(fit, blocks, axes, floor, dof, source, z, list(extra or []),
                        frozenset(), withheld, n_live)


def apply(problem: Problem, vs: VisitScatter) -> None:
    """Whiten the problem per visit with the estimated components (GLS)."""
    problem.visit = (vs.blocks.groups, whiteners(vs.blocks, vs.fit.sigma))
    problem._base_u = None


def scatter_floor(machine: Machine, artefact: Artefact, problem: Problem, groups: Groups,
                  twin, ctx, ball_jac: np.ndarray, base_pred_mm: np.ndarray, enabled: bool,
                  stated_urad: Mapping[str, float] | None, with_effects: Sequence = ()
                  ) -> VisitScatter | None:
    """Estimate the components on the twin's residuals (with ``with_effects`` — those the
    first pass selected — as fixed effects too) and whiten ``problem`` with them; None when
    disabled or when no pose was indexed more than once and no visit holds two balls."""
    from identification.gap.twin import effect_columns

    if not enabled or len(np.unique(visit_ids(groups))) < 3:
        return None
    z, axes = index_columns(machine, artefact, twin.layout, twin.p, groups.centres, groups)
    extra = [effect_columns(e, twin, groups, ctx, ball_jac, base_pred_mm) for e in with_effects]
    vs = estimate_scatter(problem, groups, z, axes, extra, stated_urad)
    vs.labels = frozenset(e.label for e in with_effects)
    apply(problem, vs)
    return vs


def rescatter(rep: dict, again: Callable[[list, frozenset], dict], machine: Machine,
              ball_ids: list[str],
              gravity_dir: Sequence[float] | None) -> dict:
    """The components were first estimated with the twin alone, so a systematic effect
    inflated them (a 2nd harmonic of C looks like C index scatter, a sag like centre scatter):
    estimate them again with the selected effects and the confounded one as fixed effects and
    redo the diagnosis — again while a pass finds another (at most ``MAX_PASSES``; each one
    hidden under the last can only show once the one above it is a fixed effect). The
    confounded ones (their likelihood-ratio test) may be attributed even where the held-out
    test of the gap, resting on a floor of few visits, is weak."""
    from identification.effects import library, sub_models

    lib = [*library(machine, ball_ids, gravity_dir=gravity_dir), *sub_models(machine)]

    def variant(family: str, axis: str | None, names) -> Effect:
        # the variant the pass named (a single harmonic or the full model: the largest one
        # whose parameters it reported), else the library's own (a profiled warm-up)
        hits = [e for e in lib if (e.family, e.axis) == (family, axis)]
        fits = [e for e in hits if set(e.param_names) <= set(names)]
        return max(fits, key=lambda e: e.n_params) if fits else hits[0]

    first, used, lr = rep, set(), set()
    for _ in range(MAX_PASSES):
        if not rep.get("scatter"):
            return rep
        sel = set(used) | {variant(s["effect"], s["axis"], s.get("params", ()))
                           for s in rep["verdict"].get("selected", [])}
        conf = rep["scatter"].get("confounded_with")
        if conf:
            sel.add(variant(conf["effect"], conf["axis"], conf.get("params", ())))
            lr.add(f"{conf['effect']}:{conf['axis']}" if conf["axis"] else conf["effect"])
        if sel <= used:
            break
        used = sel
        effects = sorted(sel, key=lambda e: (e.label, e.n_params))
        rep = again(effects, frozenset(lr))
    if rep is not first:
        rep["noise"]["source"] = first["noise"]["source"]  # the first pass' floor notes hold
        rep["scatter"]["source"] += (" — with " + ", ".join(sorted(
            e.label + (f" ({model_name(e)['model']})" if model_name(e) else "")
            for e in used)) + " as fixed effects (first pass "
            "without them: " + first["scatter"]["message"] + ")")
    return rep


def link_report(problem: Problem, twin, selected: Sequence, n_base: int) -> dict[str, dict]:
    """The twin's link errors refitted with the selected effects on the training data, under
    the diagnosis' whitening (GLS per visit when the scatter is modelled): value and standard
    uncertainty (a-posteriori factor ≥ 1, ``linear.fit``) in µrad / µm."""
    from identification.gap.linear import columns, fit

    full = fit(problem, columns(problem, [c.cols for c in selected]))
    out = {}
    for j, name in enumerate(twin.layout.links):
        k = 1e6 if name[1] in "ABC" else 1e3
        out[name] = {"value": round(float((twin.p[j] + full.beta[j]) * k), 4),
                     "std": round(float(np.sqrt(max(full.cov[j, j], 0.0)) * k), 4),
                     "unit": "urad" if name[1] in "ABC" else "um"}
    del n_base
    return out


def model_visits(machine: Machine, artefact: Artefact, problem: Problem, groups: Groups,
                 twin, ctx, ball_jac: np.ndarray, base_pred_mm: np.ndarray, enabled: bool,
                 stated_urad: Mapping[str, float] | None, with_effects: Sequence = (),
                 rivals: Sequence[np.ndarray] = ()
                 ) -> tuple[VisitScatter | None, Step | None, int, Structure | None]:
    """The visit-level model of the run: the scatter components (GLS whitening of
    ``problem``), then a moved ball (``step_ball``) on that whitening — joined to the twin's
    columns when found, and the components estimated again with it. ``rivals``: the library
    effects' columns a step must beat, and the shape of any structure along an axis the
    twin's residuals show (a local bump moves the visits of one ball that pass over it).
    Returns (scatter, step, its first column in the base, the twin's structure test — None
    when a step changed the twin)."""
    args = (machine, artefact, problem, groups, twin, ctx, ball_jac, base_pred_mm, enabled,
            stated_urad, with_effects)
    vs = scatter_floor(*args)
    found = test_structure(problem, groups, vs, problem.base)
    rivals = list(rivals)
    if found is not None and found.found and found.shape is not None:
        q = groups.centres.xyz_mm[:, AXES.index(found.axis)]
        rivals.append(found.shape.columns(q, groups.channels))
    step = find_step(problem, groups, ball_jac, rivals)
    n_step = problem.base.shape[2]
    if step is not None:
        problem.base = np.concatenate([problem.base, step.cols], axis=2)
        problem._base_u = None
        vs = scatter_floor(*args) if vs is not None else None
        found = None
    return vs, step, n_step, found


def confounded(vs: VisitScatter | None, problem: Problem, groups: Groups, cands: Sequence,
               alpha: float) -> dict | None:
    """A systematic effect of the rotary axes (a 2nd harmonic of C) enters the components as
    index scatter when they are estimated with the twin alone, and then hides under the floor
    it inflated. Each visible candidate is therefore tested by a likelihood ratio with the
    components profiled under both models (ML; dof = its visible parameters, Bonferroni over
    the candidates): the most significant one is returned ({effect, axis, p_value}) so that
    the components can be estimated again with it as a fixed effect. Only candidates whose
    F-test on the sphere fits' whitening alone (no components: nothing inflated to hide
    behind) reaches ``SCREEN_P`` are profiled."""
    if vs is None or not any(vs.finding()["components"][i]["detected"]
                             for i in range(len(vs.fit.names))) or not cands:
        return None
    cov = np.zeros((len(groups), 4, 4))
    cov[:, :3, :3] = groups.centre_cov_um2
    cov[:, 3, 3] = groups.sigma_touch_um**2
    stated = {i: float(vs.fit.sigma[i]) for i in np.flatnonzero(vs.fit.fixed)}

    def ml(x: np.ndarray) -> float:
        b = arrange(problem.y_um, x, cov, vs.z, visit_ids(groups), live(problem))
        return estimate_components(b, vs.fit.names, np.maximum(vs.fit.sigma, 0.05), stated,
                                  test=False, restricted=False).nll

    from identification.gap.attribute import f_test, test_rows
    from identification.gap.linear import fit

    cands = [c for c in cands if c.effect.label not in vs.labels]
    fixed_base = np.concatenate([problem.base, *vs.extra], axis=2)
    plain = Problem(problem.y_um, fixed_base, problem.whiten, problem.fold)
    rows = test_rows(plain)
    plain_base = fit(plain, plain.base, rows)
    screened = [c for c in cands if f_test(plain_base, fit(plain, np.concatenate(
        [plain.base, c.cols], axis=2), rows))[0] < SCREEN_P]
    if not screened:
        return None
    nll0 = ml(fixed_base)
    best = None
    for c in screened:
        lr = max(nll0 - ml(np.concatenate([fixed_base, c.cols], axis=2)), 0.0)
        p = chi2_sf(lr, c.visible_dof) * len(cands)
        if p < alpha and (best is None or p < best["p_value"]):
            best = {"effect": c.effect.family, "axis": c.effect.axis, "p_value": p,
                    "params": list(c.effect.param_names)}
    return best
