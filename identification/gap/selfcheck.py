"""Self-check of the gap diagnosis on data whose effect was withheld from the twin.

For every library family (and axis), simulate a run with the effect injected at ``factor`` × the
noise floor — measured as the RMS, over all observations, of the part of the effect the twin's
setup and link errors cannot absorb — diagnose it with a held-out split and compare. Variants
(``VARIANTS``) inject one part of a family alone: the fixed-frame 2nd-harmonic radial error
motion of a full-turn axis (order 1 and 3 in the moving frame, → ``rotary_error_motion``
on that axis). Control cases: no effect (→ ``none``), identical pre-travel for every direction
and ball (→ ``absorbed`` or ``none``: it only changes the fitted radius), an effect outside the
library — one pose displaced rigidly, as a non-repeatable indexing fault would — (→
``unexplained`` at that pose), and the rotary error motion the twin absorbs — order 0 and the
co-rotating order 1 (eccentricity) of every rotary axis, ISO 230-7 fixed frame — (→ ``none``).
Outside the library as well: a cyclic error and a local bump of each linear axis, at the sizes
a machine has rather than scaled to the floor (``selfcheck_structure``: located structure along
that axis, never ``none``).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.axis_effects import ERROR_MOTION_COMPONENTS, fixed_error_motion, order1_params
from identification.effects import FAMILIES, Effect, library, make_effect
from identification.gap.attribute import TYPICAL
from identification.gap.data import group_touches
from identification.gap.diagnose import Options, diagnose
from identification.gap.selfcheck_scatter import (
    AFTER_LIMIT_SCATTER,
    POLE,
    SCATTER_URAD,
    STEP,
    SUFFIX,
    chip_named,
    chip_pole,
    index_rms_um,
    knock,
    scatter_scenarios,
    split_scatter,
    step_named,
)
from identification.gap.selfcheck_structure import (
    AXES,
    STRUCTURE,
    caught,
    inject,
    rigid_after_ratio,
)
from identification.gap.selfcheck_structure import located as structure_located
from identification.gap.simlog import Truth, simulate
from identification.gap.twin import fit_twin
from identification.kinematics import Machine
from identification.model import Artefact, predict

CONTROLS = ("null", "uniform_pretravel", "outside", "absorbed_motion")
# Scenario → (family it must be attributed to, make_effect options of the injected part).
VARIANTS: dict[str, tuple[str, dict]] = {
    "radial2_fixed": ("rotary_error_motion", {"orders": (2,), "components": ("radial",)}),
}
SCENARIOS = (*FAMILIES, *VARIANTS, *CONTROLS)  # what ``run`` injects by default, in order
# Every library effect and the null run again under indexing
# scatter of the rotary axes, a knocked ball and a chip on the pole under the scatter.
BASE_SCENARIOS = SCENARIOS
SCENARIOS = (*BASE_SCENARIOS, *scatter_scenarios((*FAMILIES, *VARIANTS, "null")))
# Outside the library (selfcheck_structure.py): a cyclic error and a local bump of each linear
# axis, without and with the index scatter — located structure, never ``none``.
SCENARIOS = (*SCENARIOS, *STRUCTURE, *(f"{s}{SUFFIX}" for s in STRUCTURE))
ABSORBED_SIZE = 50.0  # µm / µrad of the absorbed error motion: 5× typical, still invisible
AFTER_LIMIT = 1.3  # held-out RMS with the injected family added, over the noise floor
MIN_VISIBLE = 0.3  # an injected draw must be at least this visible (RMS ratio) to the twin
MAX_DRAWS = 20


@dataclass
class Case:
    scenario: str
    axis: str | None
    plan: str
    seed: int
    verdict: str
    verdict_axis: str | None
    top: str | None
    top_axis: str | None
    after_ratio: float  # top candidate held-out RMS / noise floor
    located: bool  # outside: the displaced pose is located; structure: along its axis
    ok: bool
    family: str | None = None  # the family the scenario must be attributed to (None: control)


@dataclass
class Summary:
    cases: list[Case] = field(default_factory=list)

    def rates(self) -> dict[str, float]:
        by: dict[str, list[bool]] = defaultdict(list)
        for c in self.cases:
            by[c.scenario].append(c.ok)
        return {k: float(np.mean(v)) for k, v in by.items()}

    def table(self) -> str:
        """Confusion table, one row per injected scenario: its cases, the share diagnosed
        right, and every verdict it got with its count (full names; a 12-column matrix of
        mostly dots would not fit a terminal without cutting them)."""
        counts: dict[str, Counter] = defaultdict(Counter)
        for c in self.cases:
            counts[c.scenario][c.verdict] += 1
        rows = [s for s in SCENARIOS if s in counts]
        width = max([len("injected"), *map(len, rows)])
        head = f"{'injected':{width}s}  cases      ok  diagnosed as (cases)"
        lines = [head, "-" * len(head)]
        rates = self.rates()
        for r in rows:
            got = ", ".join(f"{v} {n}" for v, n in counts[r].most_common())
            lines.append(f"{r:{width}s}  {sum(counts[r].values()):5d}  {100 * rates[r]:4.0f} %  "
                         f"{got}")
        return "\n".join(lines)


def base_truth(machine: Machine, artefact: Artefact, rng: np.random.Generator) -> Truth:
    links = {}
    for name in machine.location_error_names():
        rot = name[1] in "ABC"
        links[name] = float(rng.normal(0.0, 15e-6 if rot else 0.015))
    return Truth(links=links, ball_setup_mm=rng.normal(0.0, 0.2, (len(artefact.balls), 3)),
                 tip_setup_mm=rng.normal(0.0, 0.05, 3))


def visible_rms(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
                 base: Truth, injected: Truth, stylus_r: float) -> tuple[float, float, float]:
    """Noise-free: (RMS of what the injection changes in the observations once the twin has
    absorbed what it can, RMS of the whole change, floor per unit touch noise)."""
    obs = []
    for tr in (base, injected):
        td = simulate(machine, artefact, poses, tr, stylus_r, 0.0, seed=0)
        obs.append(group_touches(td, artefact, stylus_r))
    g0, g1 = obs
    twin = fit_twin(machine, artefact, g0.centres)
    q, _ = predict(machine, artefact, twin.layout, twin.p, g0.centres)
    cols, _ = twin.base_columns(g0.centres, g0, q)
    y = (g1.obs_um() - g0.obs_um()).reshape(-1)
    a = cols.reshape(-1, cols.shape[2])
    norms = np.linalg.norm(a, axis=0)
    norms[norms == 0] = 1.0
    beta, *_ = np.linalg.lstsq(a / norms, y, rcond=1e-10)
    vis = float(np.sqrt(np.mean((y - (a / norms) @ beta) ** 2)))
    floor = float(np.sqrt(np.mean((np.sum(g0.to_centre**2, axis=(1, 2)) + 1.0) / 4.0)))
    return vis, float(np.sqrt(np.mean(y**2))), floor


def expected_family(scenario: str) -> str | None:
    """The family a scenario must be attributed to (None for a control)."""
    scenario = split_scatter(scenario)[0]
    if scenario in VARIANTS:
        return VARIANTS[scenario][0]
    return scenario if scenario in FAMILIES else None


def absorbed_motion(machine: Machine, rng: np.random.Generator
                    ) -> list[tuple[Effect, np.ndarray]]:
    """Order 0 (every component) and the co-rotating order 1 (radial, tilt) error motion of every
    rotary axis, fixed frame, random of ``ABSORBED_SIZE``: links and setup absorb all of it."""
    out = []
    for a in machine.rotary_axes:
        zero = fixed_error_motion(machine, a, (0,), ERROR_MOTION_COMPONENTS)
        out.append((zero, rng.normal(0.0, ABSORBED_SIZE, zero.n_params)))
        for comp in ("radial", "tilt"):
            one = fixed_error_motion(machine, a, (1,), (comp,))
            p = order1_params(machine.axes[a], comp, rng.normal(0.0, ABSORBED_SIZE, 2), True)
            out.append((one, np.array([p[n] for n in one.param_names])))
    return out


def _effect_for(scenario: str, axis: str | None, machine: Machine, artefact: Artefact,
                gravity_dir: Sequence[float] | None = None) -> Effect:
    if scenario in VARIANTS:
        family, options = VARIANTS[scenario]
        return make_effect(family, axis, machine, **options)
    if scenario == "artefact_instability":
        return make_effect(scenario, axis, machine, ball_index=artefact.ids.index(axis))
    if scenario == "gravity_sag":
        return make_effect(scenario, axis, machine, gravity_dir=gravity_dir)
    return make_effect(scenario, axis, machine)


def run_case(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
             stylus_r: float, scenario: str, axis: str | None, seed: int, plan: str = "",
             noise_um: float = 0.5, factor: float = 5.0, split: str = "auto",
             gravity_dir: Sequence[float] | None = None) -> Case:
    rng = np.random.default_rng(seed)
    base = base_truth(machine, artefact, rng)
    truth = Truth(base.links, base.ball_setup_mm, base.tip_setup_mm)
    displaced = knocked = None
    family = expected_family(scenario)
    name, (scenario, scattered) = scenario, split_scatter(scenario)
    if family is not None:
        eff = _effect_for(scenario, axis, machine, artefact, gravity_dir)
        typical = np.array([TYPICAL.get(u, 1.0) for u in eff.units])
        # Draw a random parameter vector of typical size; redraw one that is mostly absorbed by
        # the twin (scaling its small visible part up to 5× the floor would inject an absurd
        # effect — e.g. 300 µm of pre-travel — and test non-linearities instead).
        for _ in range(MAX_DRAWS):
            theta = rng.normal(size=eff.n_params) * typical
            truth.effects = [(eff, theta)]
            vis, total, _ = visible_rms(machine, artefact, poses, base, truth, stylus_r)
            if vis >= MIN_VISIBLE * total:
                break
    elif scenario == "outside":
        displaced = int(rng.integers(1, len(poses) - 1))
        v = rng.normal(size=3)
        truth.pose_offsets_mm = {displaced: v / np.linalg.norm(v) * 1e-3}
    elif scenario == "uniform_pretravel":
        eff = make_effect("probe_pretravel", None, machine)
        truth.effects = [(eff, np.full(5, factor * noise_um))]
    elif scenario == "absorbed_motion":
        truth.effects = absorbed_motion(machine, rng)
    elif scenario == STEP:
        knocked = knock(rng, len(artefact.balls), len(poses))
        truth.ball_steps = [(knocked.ball, knocked.t_s, knocked.vector_mm)]
    elif scenario in STRUCTURE:  # the sizes, not scaled to the floor
        truth.effects = [inject(scenario, axis, machine, artefact, poses, rng)]
    if family is not None or scenario == "outside":
        vis, _, unit_floor = visible_rms(machine, artefact, poses, base, truth, stylus_r)
        floor = np.hypot(unit_floor * noise_um, index_rms_um(machine, artefact, poses,
                                                            SCATTER_URAD if scattered else 0.0))
        k = factor * floor / max(vis, 1e-12)
        truth.effects = [(e, p * k) for e, p in truth.effects]
        truth.pose_offsets_mm = {i: o * k for i, o in truth.pose_offsets_mm.items()}
    if scattered:  # after the scaling: visible_rms compares runs without it
        truth.index_std_urad = {a: SCATTER_URAD for a in machine.rotary_axes}
    data = simulate(machine, artefact, poses, truth, stylus_r, noise_um, seed=seed + 7919)
    chip = chip_pole(rng, data, len(artefact.balls)) if scenario == POLE else None
    rep = diagnose(machine, artefact, data, stylus_r,
                   options=Options(split=split, gravity_dir=gravity_dir))
    top = rep["candidates"][0] if rep["candidates"] else None
    floor = rep["noise_floor_um"]
    after = (top["holdout_rms_um"] / floor) if top else float("nan")
    v = rep["verdict"]
    limit = AFTER_LIMIT_SCATTER if scattered else AFTER_LIMIT
    located = scenario in STRUCTURE and structure_located(rep, axis, limit)
    if displaced is not None:
        b, c = poses[displaced]
        key = f"b={round(b, 3):g},c={round(c, 3):g}"
        located = any(x["by"] == "pose" and x["key"] == key for x in rep["location"])
    if family is not None:
        ok = (top is not None and top["effect"] == family and top["axis"] == axis
              and v["effect"] == family
              and after <= (AFTER_LIMIT_SCATTER if scattered else AFTER_LIMIT))
    elif scenario in STRUCTURE:
        ok = located and caught(rep, limit)
        after = rigid_after_ratio(rep)
    elif knocked is not None:
        ok = step_named(rep, knocked, artefact.ids)
    elif chip is not None:
        ok = chip_named(rep, chip, artefact.ids)
    elif scenario in ("null", "absorbed_motion"):
        ok = v["effect"] == "none"
    elif scenario == "uniform_pretravel":
        ok = v["effect"] in ("none", "absorbed")
    else:
        ok = v["effect"] == "unexplained" and located
    return Case(name, axis, plan, seed, v["effect"], v["axis"],
                top["effect"] if top else None, top["axis"] if top else None, after, located, ok,
                family)


def visible(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
            stylus_r: float, family: str, axis: str | None,
            gravity_dir: Sequence[float] | None = None) -> bool:
    """Would a typical-size instance be seen at all (> 1 % of the floor) on these poses?"""
    rng = np.random.default_rng(0)
    base = base_truth(machine, artefact, rng)
    eff = _effect_for(family, axis, machine, artefact, gravity_dir)
    theta = np.array([TYPICAL.get(u, 1.0) for u in eff.units])
    inj = Truth(base.links, base.ball_setup_mm, base.tip_setup_mm, [(eff, theta)])
    vis, _, unit_floor = visible_rms(machine, artefact, poses, base, inj, stylus_r)
    return vis > 0.01 * unit_floor * 0.5


def axes_of(scenario: str, machine: Machine, artefact: Artefact) -> list[str | None]:
    """The scenario's instances in the library (axes or ball ids; [None] without an axis); a
    variant of the rotary error motion on the full-turn axes only (its orders need the turn)."""
    scenario = split_scatter(scenario)[0]
    if scenario in VARIANTS:
        return [a for a in machine.rotary_axes
                if np.ptp(machine.axes[a].travel) >= 360.0]
    if scenario in STRUCTURE:
        return [a for a in AXES if a in machine.linear_axes]
    return [e.axis for e in library(machine, artefact.ids) if e.family == scenario]


def run(machine: Machine, artefact: Artefact, plans: dict[str, Sequence[tuple[float, float]]],
        stylus_r: float, seeds: int,
        scenarios: Sequence[str] = SCENARIOS,
        skip: Sequence[tuple[str, str | None]] = (), progress=None, split: str = "auto",
        gravity_dir: Sequence[float] | None = None) -> Summary:
    """Every scenario × plan × seed; a family's axis cycles with the seed. ``skip`` lists
    instances that are invisible on the machine (e.g. angular motion of the axis carrying a
    zero-length tool) — they are reported by the diagnosis as invisible, not tested here."""
    out = Summary()
    for plan, poses in plans.items():
        for sc in scenarios:
            fam = expected_family(sc)
            bare = split_scatter(sc)[0]
            axes = axes_of(sc, machine, artefact) if fam is not None or bare in STRUCTURE \
                else [None]
            axes = [a for a in axes if (bare, a) not in skip
                    and (fam is None or visible(machine, artefact, poses, stylus_r, bare, a,
                                                   gravity_dir))]
            axes = axes or [None]
            for s in range(seeds):
                ax = axes[s % len(axes)]
                case = run_case(machine, artefact, poses, stylus_r, sc, ax, 1000 * s + 17,
                                plan, split=split, gravity_dir=gravity_dir)
                out.cases.append(case)
                if progress:
                    progress(case)
    return out


def grid_49() -> list[tuple[float, float]]:
    """7 × 7 poses: B −45…45° step 15°, C in seven equal steps of the full turn."""
    return [(b, round(c, 6)) for b in range(-45, 46, 15) for c in np.arange(7) * 360.0 / 7]
