"""`rumba plan --map`: the placements and indexations of a map of the linear axes that cover a
volume within a machine-time budget, and what each placement adds.

Each placement is an artefact file (where the operator sets the balls); its candidate plans are
B × C grids over the machine's rotary strokes (B within ±``tilt_max_deg``, C round its circle),
each generated and checked against travel limits and keep-outs like any program and timed by
the cycle-time estimate (``programs.cycletime``). The ball centres the nominal machine reaches
at the grid's poses are the stroke it covers on X, Y and Z. The choice, over every combination
of one grid (or none) per placement within the budget: the largest covered fraction of the
target box on its worst axis, then the most indexations (the terms better determined), then the
least time. What each placement adds is said in the map's own terms
(``identification.linmap.observe``): the stroke it adds per axis, the map terms that become
observable with it, and the terms whose predicted standard uncertainty it lowers.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from contracts.setup_files import Plan, load_artefact, load_machine, plan_from_dict
from identification.identifiability import nominal_centres
from identification.kinematics import Machine
from identification.linmap.observe import Observability, observable_terms, predicted_std
from identification.linmap.problem import Placement
from identification.linmap.terms import candidate_terms
from identification.model import Artefact
from programs.generate import generate
from programs.geometry import ProgramError
from programs.safety import SafetyError

# (B levels, C levels) tried per placement, fewest indexations first
GRIDS = ((2, 3), (3, 3), (3, 4), (3, 6), (4, 6), (4, 8), (4, 9), (5, 9))
MAX_DEGREE = 4  # the map's default degree cap (rumba map --max-degree)
BETTER = 1.5  # a term is "better determined" when a placement divides its u by this or more
PLAN_SETTINGS: dict[str, Any] = {  # the shipped map plans' probing settings
    "stylus_diameter_mm": 6, "feeds": {"probe_mm_min": 300, "approach_mm_min": 2000},
    "standoff_mm": 2, "overtravel_mm": 2, "clearance_mm": 10}


class MapPlanError(ValueError):
    """The map cannot be planned as asked (bad input, nothing reachable, budget too small):
    the message says why and what would do."""


@dataclass(frozen=True)
class Candidate:
    """One placement probed at one grid: its checked program's time and covered stroke."""

    placement: int
    grid: tuple[int, int]
    plan: Plan
    seconds: float
    touches: int
    centres: Any  # identification.model.Centres of the nominal machine
    box_mm: dict[str, tuple[float, float]]


@dataclass(frozen=True)
class Step:
    """What one placement of the chosen plan adds to those before it."""

    candidate: Candidate
    artefact_path: Path
    artefact: Artefact
    covered_mm: dict[str, tuple[float, float]]  # union of the placements so far
    added_mm: dict[str, float]  # stroke added on each axis (mm)
    new_terms: tuple[str, ...]  # map terms observable from this placement on
    better: dict[str, tuple[float, float]]  # term → (u before, u after), µm or µrad
    observability: Observability


@dataclass(frozen=True)
class MapPlan:
    machine: Machine
    steps: tuple[Step, ...]
    target_mm: dict[str, tuple[float, float]]
    budget_s: float
    coverage: dict[str, float]  # covered fraction of the target per axis
    refused: tuple[str, ...] = ()  # candidate grids the safety check refused, with why
    notes: list[str] = field(default_factory=list)

    @property
    def seconds(self) -> float:
        return sum(s.candidate.seconds for s in self.steps)


def grid_poses(machine: Machine, nb: int, nc: int, tilt_max_deg: float
               ) -> list[tuple[float, float]]:
    """``nb`` tilt levels within ±tilt_max_deg (and the first rotary axis' travel) × ``nc``
    angles round the second rotary axis (its travel when it is not a full turn)."""
    r1, r2 = (machine.axes[a] for a in machine.rotary_axes[:2])
    lo, hi = max(-tilt_max_deg, r1.travel[0]), min(tilt_max_deg, r1.travel[1])
    if hi - lo < 1.0:
        raise MapPlanError(f"{machine.name}: axis {machine.rotary_axes[0]} has no tilt within "
                           f"±{tilt_max_deg:g}° in its travel {list(r1.travel)}")
    b = np.linspace(lo, hi, nb)
    c0, c1 = r2.travel
    c = (np.arange(nc) * 360.0 / nc if c1 - c0 >= 360.0 else np.linspace(c0, c1, nc))
    return [(round(float(x), 3), round(float(y), 3)) for x in b for y in c]


def _candidates(machine_path: Path, artefacts: Sequence[Artefact], dialect: str,
                settings: dict[str, Any], tilt_max_deg: float
                ) -> tuple[list[list[Candidate]], list[str]]:
    machine, mf = load_machine(machine_path)
    out: list[list[Candidate]] = []
    refused: list[str] = []
    for i, art in enumerate(artefacts):
        mine = []
        for nb, nc in GRIDS:
            poses = grid_poses(machine, nb, nc, tilt_max_deg)
            data = {**settings, "name": f"map-P{i + 1}-{len(poses)}poses",
                    "poses": [{"b_deg": b, "c_deg": c} for b, c in poses]}
            plan = plan_from_dict(data, f"<map plan P{i + 1}>")
            try:
                prog = generate(machine, mf, art, plan, dialect)
            except (SafetyError, ProgramError) as e:
                refused.append(f"P{i + 1} ({art.name}) {nb}×{nc} grid: {e}")
                continue
            c = nominal_centres(machine, art, poses)
            box = {a: (float(c.xyz_mm[:, j].min()), float(c.xyz_mm[:, j].max()))
                   for j, a in enumerate("XYZ")}
            mine.append(Candidate(i, (nb, nc), plan, prog.estimated_s, len(prog.touches), c,
                                  box))
        out.append(mine)
    return out, refused


def _union(boxes: Sequence[dict[str, tuple[float, float]]]) -> dict[str, tuple[float, float]]:
    return {a: (min(b[a][0] for b in boxes), max(b[a][1] for b in boxes)) for a in "XYZ"}


def _coverage(box: dict[str, tuple[float, float]], target: dict[str, tuple[float, float]]
              ) -> dict[str, float]:
    out = {}
    for a, (lo, hi) in target.items():
        c0, c1 = max(box[a][0], lo), min(box[a][1], hi)
        out[a] = max(c1 - c0, 0.0) / (hi - lo)
    return out


def choose(cands: list[list[Candidate]], target: dict[str, tuple[float, float]],
           budget_s: float) -> tuple[Candidate, ...] | None:
    """The combination (one grid or none per placement) within the budget that covers the
    most of the target on its worst axis, then has the most indexations, then the least time;
    None when not even one placement fits."""
    best, key = None, None
    for combo in itertools.product(*[[None, *c] for c in cands]):
        used = tuple(c for c in combo if c is not None)
        t = sum(c.seconds for c in used)
        if not used or t > budget_s:
            continue
        cov = min(_coverage(_union([c.box_mm for c in used]), target).values())
        k = (round(cov, 3), sum(len(c.plan.poses) for c in used), -t)
        if key is None or k > key:
            best, key = used, k
    return best


def cheapest_covering(cands: list[list[Candidate]], target: dict[str, tuple[float, float]],
                      min_coverage: float) -> float:
    """The least machine time (s) of a combination covering ``min_coverage`` of the target on
    every axis; inf when none does."""
    best = float("inf")
    for combo in itertools.product(*[[None, *c] for c in cands]):
        used = [c for c in combo if c is not None]
        if used and min(_coverage(_union([c.box_mm for c in used]), target).values()) \
                >= min_coverage:
            best = min(best, sum(c.seconds for c in used))
    return best


def _steps(machine: Machine, used: Sequence[Candidate], artefacts: Sequence[Artefact],
           paths: Sequence[Path]) -> tuple[Step, ...]:
    ranges = _union([c.box_mm for c in used])
    terms = candidate_terms("XYZ", MAX_DEGREE)
    placements: list[Placement] = []
    steps: list[Step] = []
    before_terms: set[str] = set()
    before_u: dict[str, float] = {}
    before_box: dict[str, tuple[float, float]] | None = None
    for c in used:
        placements.append(Placement(f"P{len(placements) + 1}", artefacts[c.placement],
                                    c.centres))
        obs = observable_terms(machine, placements, terms, ranges)
        u = predicted_std(machine, placements, obs, ranges)
        box = _union([p.box_mm for p in used[:len(placements)]])
        added = {a: (box[a][1] - box[a][0]) - ((before_box[a][1] - before_box[a][0])
                                               if before_box else 0.0) for a in "XYZ"}
        names = [t.name for t in obs.terms]
        better = {n: (before_u[n], u[n]) for n in names
                  if n in before_u and u[n] * BETTER <= before_u[n]}
        steps.append(Step(c, paths[c.placement], artefacts[c.placement], box, added,
                          tuple(n for n in names if n not in before_terms), better, obs))
        before_terms, before_u, before_box = set(names), u, box
    return tuple(steps)


def plan_map(machine_path: Path, artefact_paths: Sequence[Path], budget_s: float,
             dialect: str = "fanuc", box_mm: dict[str, tuple[float, float]] | None = None,
             min_coverage: float = 0.5, tilt_max_deg: float = 60.0,
             settings: dict[str, Any] | None = None) -> MapPlan:
    """The map plan (module doc); ``MapPlanError`` when the budget or the placements cannot
    cover ``min_coverage`` of the target (``box_mm``, or the machine's strokes) on every axis."""
    if not 0 < budget_s <= 24 * 3600:
        raise MapPlanError(f"--budget-min {budget_s / 60:g}: expected minutes in (0, 1440]")
    if not 0 < min_coverage <= 1:
        raise MapPlanError(f"--min-coverage {min_coverage:g}: expected a fraction in (0, 1]")
    if not 0 < tilt_max_deg <= 180:
        raise MapPlanError(f"--tilt-max-deg {tilt_max_deg:g}: expected degrees in (0, 180]")
    machine, _ = load_machine(machine_path)
    strokes = {a: (float(machine.axes[a].travel[0]), float(machine.axes[a].travel[1]))
               for a in "XYZ"}
    target = strokes if box_mm is None else box_mm
    for a, (lo, hi) in target.items():
        s0, s1 = strokes[a]
        if not lo < hi or lo < s0 or hi > s1:
            raise MapPlanError(f"--box: {a} {lo:g}..{hi:g} mm: expected lo < hi within the "
                               f"stroke {s0:g}..{s1:g} mm of {machine.name}")
    artefacts = [load_artefact(p) for p in artefact_paths]
    cands, refused = _candidates(machine_path, artefacts, dialect,
                                 settings or PLAN_SETTINGS, tilt_max_deg)
    if not any(cands):
        raise MapPlanError("no candidate grid of any placement passes the safety check: "
                           + "; ".join(refused[:3]))
    cheapest = min(c.seconds for cs in cands for c in cs)
    used = choose(cands, target, budget_s)
    if used is None:
        raise MapPlanError(f"budget {budget_s / 60:.1f} min: the smallest checked placement "
                           f"program takes {cheapest / 60:.1f} min")
    everything = _union([c.box_mm for cs in cands for c in cs])
    reach = _coverage(everything, target)
    cov = _coverage(_union([c.box_mm for c in used]), target)
    short = {a: f for a, f in cov.items() if f < min_coverage}
    if short:
        need = cheapest_covering(cands, target, min_coverage)
        what = ", ".join(f"{a} {100 * f:.0f} %" for a, f in short.items())
        if any(reach[a] < min_coverage for a in short):
            raise MapPlanError(
                f"these placements cannot cover {100 * min_coverage:.0f} % of the target on "
                f"every axis whatever the budget (at most " + ", ".join(
                    f"{a} {100 * reach[a]:.0f} %" for a in "XYZ") + "): add a placement that "
                "reaches further, or give a smaller --box")
        raise MapPlanError(f"budget {budget_s / 60:.1f} min covers only {what} of the target "
                           f"({100 * min_coverage:.0f} % asked); the placements given cover "
                           f"it in {need / 60:.1f} min")
    return MapPlan(machine, _steps(machine, used, artefacts, list(artefact_paths)), target,
                   budget_s, cov, tuple(refused))
