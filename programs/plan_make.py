"""Make a plan: choose the B/C poses and their order that reach target link uncertainties in
the least machine time, as a checked program and a plan file, with the reference plan's program
and predictions beside it (``rumba plan`` prints and writes what this returns)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

from contracts.setup_files import (
    Plan,
    check_touch_count,
    load_artefact,
    load_machine,
    load_plan,
)
from identification.kinematics import Machine
from programs.dialects import get_dialect
from programs.generate import GeneratedProgram, generate
from programs.geometry import ProgramError
from programs.optimise import Chosen
from programs.plan_drift import DriftPlan
from programs.safety import SafetyError


class PlanMakeError(Exception):
    """A plan cannot be made from these files and targets; the message names the file or key
    and what was expected."""


REFUSED_RETRIES = 5  # searches in one `rumba plan` when the whole program refuses a pose


@dataclass
class Outcome:
    """What ``make_plan`` found: the plan written, both programs, predictions, timings."""

    plan: Plan  # the optimised plan, as the loader reads it
    text: str  # its file
    reference: Plan
    new: GeneratedProgram
    old: GeneratedProgram
    links: tuple[str, ...]
    targets: dict[str, float]
    new_u: dict[str, float]
    ref_u: dict[str, float]
    drift_u: dict[str, float] | None
    chosen: Chosen
    optimiser_s: float
    drift: tuple[DriftPlan, DriftPlan] | None = None  # reference, optimised
    assumed_index: str = ""  # the indexing repeatability the predictions assume, in words


def make_plan(machine_path: Path, artefact_path: Path, target_path: Path, dialect: str,
              max_time_s: float | None = None) -> Outcome:
    """The whole of ``rumba plan`` but printing and writing (also for benchmarks/bench_plan);
    ``PlanMakeError`` when the files or targets do not allow a plan."""
    from contracts.plan_targets import load_targets_file, reference_path
    from programs.design import max_links
    from programs.optimise import Problem, candidate_poses, optimise
    from programs.plan_drift import drift_plan, plan_times_s
    from programs.plan_report import (
        estimate_visits,
        plan_links,
        plan_yaml,
        predicted_u,
        to_plan,
        to_plan_dict,
    )

    if max_time_s is not None and not 0 < max_time_s <= 1e6:
        raise PlanMakeError(f"--max-time {max_time_s:g}: expected seconds in (0, 1e6]")
    machine, mf = load_machine(machine_path)
    artefact = load_artefact(artefact_path)
    tf = load_targets_file(target_path)
    ref_file = reference_path(tf, target_path)
    ref = load_plan(ref_file)
    check_touch_count(ref, artefact, f"{ref_file}: poses")
    sigma = (tf.repeatability_um[0], tf.repeatability_um[1], tf.repeatability_um[2])
    # the machine file's stated rotary repeatability: the estimator's index components
    #, so the predicted u are its visit sandwich under them
    index = {a: float(v) for a, v in (mf.rotary_repeatability_urad or {}).items()} or None
    d = get_dialect(dialect)

    def program(plan: Plan, what: str) -> GeneratedProgram:
        try:
            return generate(machine, mf, artefact, plan, dialect)
        except (SafetyError, ProgramError) as e:
            raise PlanMakeError(f"{what}: {e}") from None

    ref_links, _ = plan_links(machine, artefact, ref)
    grid_links, dropped = max_links(machine, artefact, candidate_poses(machine, tf.candidates))
    for name, want in tf.links.items():
        if name not in grid_links:
            why = dropped.get(name, "not a location error of this machine")
            raise PlanMakeError(f"{target_path}: links.{name}: not identifiable on "
                         f"{machine.name} with {artefact.name} (absorbed by {why})")
        if want == "reference" and name not in ref_links:
            raise PlanMakeError(f"{target_path}: links.{name}: 'reference', but {ref_file.name} "
                         f"does not identify {name}")
    ref_u, _ = predicted_u(machine, artefact, ref, ref_links, sigma, index_urad=index)
    targets = {k: (ref_u[k] if v == "reference" else float(v)) for k, v in tf.links.items()}
    fast = mf.dynamics.max_probe_feed_mm_min
    feeds = ref.feeds.model_copy(update={
        "fast_probe_mm_min": fast if tf.two_speed and fast > ref.feeds.probe_mm_min else None})
    probing = ref.model_copy(update={"feeds": feeds,
                                     "clearance_mm": tf.clearance_mm or ref.clearance_mm})
    problem = Problem(machine, mf, artefact, probing, grid_links, targets, sigma,
                      tf.candidates, d.two_speed and feeds.fast_probe_mm_min is not None,
                      tf.validate_poses, max_time_s, index)
    t0 = time.perf_counter()

    def search(problem: Problem) -> tuple[Problem, Chosen, Plan, GeneratedProgram]:
        """The optimiser's plan as a checked program. Each visit was checked alone; the moves
        into a pose depend on the pose before it, so a pose the whole program refuses is
        excluded and the search runs again (a handful of times at most)."""
        last = ""
        for _ in range(REFUSED_RETRIES):
            chosen = optimise(problem)
            plan = to_plan(chosen, probing, tf.name)
            try:
                return problem, chosen, plan, generate(machine, mf, artefact, plan, dialect)
            except SafetyError as e:
                if e.pose is None:
                    raise PlanMakeError(f"the optimised plan is refused: {e}") from None
                last = str(e)
                problem = replace(problem, refused=(*problem.refused,
                                                    (chosen.candidates[e.pose], last)))
            except ProgramError as e:
                raise PlanMakeError(f"the optimised plan is refused: {e}") from None
        raise PlanMakeError(f"the optimised plan is refused {REFUSED_RETRIES} times, last: {last}")

    try:
        problem, chosen, plan, new = search(problem)
        for _ in range(3):  # the search's time model is approximate: honour the cap exactly
            if max_time_s is None or new.estimated_s <= max_time_s:
                break
            problem = replace(problem, max_time_s=problem.max_time_s * max_time_s
                              / new.estimated_s)  # type: ignore[operator]
            problem, chosen, plan, new = search(problem)
    except ValueError as e:
        cap = f" (--max-time {max_time_s:g} s)" if max_time_s is not None else ""
        raise PlanMakeError(f"{target_path}: {e}{cap}; targets missed: {', '.join(targets)}") \
            from None
    opt_s = time.perf_counter() - t0
    got, _ = plan_links(machine, artefact, plan)
    if set(got) != set(grid_links):
        raise PlanMakeError(f"the optimised plan identifies {sorted(got)}, not {sorted(grid_links)}"
                     ": make the candidate grid finer")
    old = program(ref, f"{ref_file}")
    new_u, new_du = predicted_u(machine, artefact, plan, grid_links, sigma,
                                chosen.visit_times_h, index)
    assumed = index_assumption(machine, index, Path(machine_path).name)
    header = [f"rumba plan {time.strftime('%Y-%m-%d %H:%M')}: {machine.name} x "
              f"{artefact.name}, from {Path(target_path).name}",
              f"{len(chosen.poses)} poses + the first again (drift check), estimated "
              f"{new.estimated_s:.0f} s ({dialect}); reference {ref.name}: "
              f"{old.estimated_s:.0f} s",
              "predicted link u (µrad / µm, σ = " + "/".join(f"{s:g}" for s in sigma)
              + " µm): " + ", ".join(f"{k} {new_u[k]:.3g}" for k in grid_links),
              f"assumed {assumed}"]
    text = plan_yaml(to_plan_dict(chosen, probing, tf.name), header)
    drift = (drift_plan(machine, artefact, estimate_visits(ref),
                        plan_times_s(ref, old.estimated_s), ref_links, sigma, index),
             drift_plan(machine, artefact, estimate_visits(plan),
                        [h * 3600.0 for h in chosen.visit_times_h], grid_links, sigma, index))
    return Outcome(plan, text, ref, new, old, grid_links, targets, new_u, ref_u, new_du,
                   chosen, opt_s, drift, assumed)


def index_assumption(machine: Machine, index: dict[str, float] | None, source: str) -> str:
    """What the predictions assume of the rotary indexing, in words: "B/C indexing
    repeatability 4 µrad (machine file thesis.yaml)", or that nothing was stated."""
    axes = machine.rotary_axes[:2]
    if not index or not any(index.get(a, 0.0) > 0 for a in axes):
        return ("exact rotary indexing (the machine file states no "
                "rotary_repeatability_urad: a visit's balls share no index error)")
    vals = {a: index.get(a, 0.0) for a in axes}
    if len(set(vals.values())) == 1:
        said = f"{'/'.join(axes)} indexing repeatability {vals[axes[0]]:g} µrad"
    else:
        said = "indexing repeatability " + ", ".join(f"{a} {v:g} µrad" for a, v in vals.items())
    return f"{said} 1σ per indexation (machine file {source})"
