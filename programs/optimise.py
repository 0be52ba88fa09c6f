"""``rumba plan``: the B/C poses, and their order, that reach a target standard uncertainty on
every link in the least estimated machine time — optimal experimental design with a cost.

Criterion (Atkinson, Donev & Tobias, *Optimum Experimental Designs, with SAS*, OUP 2007, ch. 10:
A-optimality, weighted): the predicted link uncertainties ``u`` of ``programs.design`` (the
covariance the estimator reports, (JᵀWJ)⁻¹ with the centre repeatability σ; with a stated
rotary repeatability its visit sandwich, where revisits and extra indexations count), scaled
by their targets, φ = Σ (u_k / target_k)²; a plan is feasible when every u_k ≤ target_k. Cost: the
cycle-time model's seconds of each visit (``programs.candidates``) and of the moves between
visits. The revisit of the first pose (drift check) counts twice in the information.

Search: (1) greedy forward selection with cost-weighted gain — add the candidate with the
largest drop of φ per second of its visit until every target is met (Cook & Fedorov, "Constrained
optimization of experimental design", Statistics 26, 1995: gain per unit cost); (2) exchange
(Fedorov, *Theory of Optimal Experiments*, 1972; Atkinson et al. ch. 12): drop a pose, swap one
for any candidate, or move the revisit, whenever the result stays feasible and gets faster (or,
while infeasible, gets closer); repeat to a local optimum. A pose enters a design only once its
one-pose program has passed the safety check (lazy: the candidates a design actually wants).
(3) Order: ``programs.plan_order``. The thesis has no pose-selection method (its annex-B set is
a regular B/C sweep); §4.3.1 shows the B range drives the setup/offset coupling, which is
why the candidate grid spans the whole reachable B travel.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import numpy as np

from contracts.plan_targets import CandidateGrid
from contracts.setup_files import MachineFile, Plan
from identification.kinematics import Machine
from identification.model import Artefact
from programs.candidates import Candidates
from programs.design import Design, build_design, drift_u_worst, link_u, link_u_regular
from programs.plan_order import order_tour, unwrap_c

MAX_STEPS = 60  # exchange steps (each the best of every drop / swap / revisit move)
# A hard stop, reported, should a slow machine reach it: seconds of this thread's CPU, not of the
# clock, so that a busy PC (a CI box at load 10 took 4× the wall time) ends the same search with
# the same plan; the search itself takes ~2 s of CPU on the shipped files.
DEADLINE_S = 20.0
RIDGE = 1e-9  # relative prior on every parameter so that φ exists before the plan is full rank
MET = 1.0 - 1e-6  # a target counts as met below this ratio (the ridge must not decide it)
# Scores within this relative precision are ties, broken by the candidate's index. The greedy's
# first picks compare plans that are not yet full rank, whose gains (~1/RIDGE) differ between
# candidates that resolve as many directions only by rounding, and rounding changes with the BLAS
# kernel and thread count: without this the same files gave another plan on another CPU.
TIE_REL = 1e-6


def settled(x: np.ndarray) -> np.ndarray:
    """``x`` rounded to ``TIE_REL`` of its largest finite magnitude (near-ties become ties)."""
    fin = np.abs(x[np.isfinite(x)])
    if fin.size == 0 or fin.max() == 0.0:
        return x
    q = TIE_REL * float(fin.max())
    return np.where(np.isfinite(x), np.round(x / q) * q, x)


@dataclass(frozen=True)
class Problem:
    """What ``optimise`` is asked: links and their targets, the probing of the plan to write."""

    machine: Machine
    machine_file: MachineFile
    artefact: Artefact
    probing: Plan  # stylus, feeds, standoff, overtravel, clearance of the plan written
    links: tuple[str, ...]  # the identifiable set the estimator will estimate
    targets: dict[str, float]  # µrad / µm, a subset of ``links``
    sigma_um: tuple[float, float, float]
    grid: CandidateGrid = field(default_factory=CandidateGrid)
    two_speed: bool = False  # the dialect can repeat a probing move
    validate_poses: int = 0
    max_time_s: float | None = None
    # the machine file's stated rotary repeatability (µrad 1σ per indexation by axis letter):
    # the predicted u are the estimator's visit sandwich under it (``programs.design``)
    index_urad: dict[str, float] | None = None
    # candidates (indices into ``candidate_poses``) whose pose the whole program refused after
    # an earlier search: a visit is checked alone, the moves into it only in the whole program
    refused: tuple[tuple[int, str], ...] = ()  # (candidate, the program's reason)


@dataclass
class Chosen:
    """The optimiser's answer: poses in run order, the first revisited at the end."""

    poses: list[tuple[float, float]]  # run order, C unwrapped
    roles: list[str]
    candidates: list[int]  # candidate index per pose
    predicted_u: dict[str, float]  # the estimate-role visits + the revisit
    missed: dict[str, tuple[float, float]]  # link → (u, target) when --max-time binds
    surrogate_s: float  # the search's estimate of the run (the program's own comes later)
    builds: int  # one-pose programs built and checked
    excluded: list[str] = field(default_factory=list)  # candidates refused by safety (why)
    runtime_s: float = 0.0
    design: Design | None = None
    visit_times_h: list[float] = field(default_factory=list)  # estimate visits + revisit
    stopped: bool = False  # the search hit DEADLINE_S (a local optimum was not confirmed)
    # poses a whole program refused (the moves into them), excluded from this search
    refused: list[str] = field(default_factory=list)


def candidate_poses(machine: Machine, grid: CandidateGrid) -> list[tuple[float, float]]:
    """The B/C grid within both rotary travels (B symmetric about 0, C over one turn)."""
    r1, r2 = machine.rotary_axes
    lo, hi = grid.b_range_deg or machine.axes[r1].travel
    lo, hi = max(lo, machine.axes[r1].travel[0]), min(hi, machine.axes[r1].travel[1])
    b = np.arange(np.ceil(lo / grid.b_step_deg), np.floor(hi / grid.b_step_deg) + 1)
    c_lo, c_hi = machine.axes[r2].travel
    cs = []
    for c in np.arange(0.0, 360.0 - 1e-9, grid.c_step_deg):
        fit = [c + s for s in (0.0, -360.0, 360.0) if c_lo <= c + s <= c_hi]
        if fit:
            cs.append(round(float(fit[0]), 6))
    return [(round(float(x * grid.b_step_deg), 6), c) for x in b for c in cs]


class _Search:
    def __init__(self, pb: Problem, design: Design, cands: Candidates) -> None:
        self.pb, self.d, self.c = pb, design, cands
        self.tidx = np.array([pb.links.index(k) for k in pb.targets])
        self.tval = np.array(list(pb.targets.values()))
        n = len(design.poses)
        self.excluded = np.zeros(n, bool)
        scale = np.einsum("kii->i", design.info).sum() / n
        self.ridge = np.eye(design.layout.size) * RIDGE * max(scale, 1e-30)
        dyn = pb.machine_file.dynamics
        # one move between visits, before the tour is known: a 60° index, 2 × 100 mm of rapid
        self.t_move = dyn.rotary_clamp_s + 60.0 / dyn.rotary_rapid_deg_min * 60.0 + \
            200.0 * cands.rapid_s_per_mm

    def counts(self, sel: list[int], r: int) -> np.ndarray:
        w = np.zeros(len(self.d.poses))
        for s in sel:
            w[s] += 1
        if sel:
            w[sel[r]] += 1
        return w

    def ratio(self, m: np.ndarray, extra: np.ndarray | None = None) -> np.ndarray:
        u = link_u_regular(self.d, m + self.ridge, extra)[..., self.tidx]
        return u / self.tval

    def ratio_of(self, w: np.ndarray) -> np.ndarray:
        """Target ratios of the plan of visit counts ``w``."""
        return self.ratio(self.d.info_of(w), self.d.meat_of(w))

    def ratio_plus(self, w: np.ndarray, avail: np.ndarray, mult: float) -> np.ndarray:
        """Target ratios of ``w`` plus ``mult`` visits of each candidate in ``avail``."""
        s = self.d.meat_of(w)
        return self.ratio(self.d.info_of(w)[None] + mult * self.d.info[avail],
                          None if s is None else s[None] + mult * self.d.index_info[avail])

    def costs(self) -> np.ndarray:
        return self.c.costs()

    def total(self, sel: list[int], r: int, cost: np.ndarray) -> float:
        return float(self.counts(sel, r) @ cost + len(sel) * self.t_move) if sel else 0.0

    def score(self, ratio_max: np.ndarray, total: np.ndarray) -> np.ndarray:
        """Lower is better: within --max-time, feasible, then faster (or, infeasible, closer)."""
        over = np.zeros_like(total) if self.pb.max_time_s is None else \
            (total > self.pb.max_time_s)
        feas = ratio_max <= MET
        return over * 4e9 + (~feas) * 2e9 + np.where(feas, total, np.minimum(ratio_max, 1e9))

    # ------------------------------------------------------------------ moves
    def greedy(self, sel: list[int], r: int) -> list[int]:
        while True:
            cost = self.costs()
            rat = self.ratio_of(self.counts(sel, r))
            if rat.max() <= MET:
                return sel
            avail = np.flatnonzero(~self.excluded & (self.counts(sel, r) == 0))
            if avail.size == 0:
                return sel
            mult = 1.0 if sel else 2.0  # the first pose is the revisited one
            phi0 = float(np.sum(rat ** 2))
            phi = np.sum(self.ratio_plus(self.counts(sel, r), avail, mult) ** 2, axis=1)
            add = mult * (cost[avail] + self.t_move)
            gain = (phi0 - phi) / add
            if self.pb.max_time_s is not None:
                fits = self.total(sel, r, cost) + add <= self.pb.max_time_s
                if not fits.any():
                    return sel
                gain = np.where(fits, gain, -np.inf)
            pick = int(avail[int(np.argmax(settled(gain)))])
            if not self.c.visit(pick).ok:
                self.excluded[pick] = True
                continue
            sel = [*sel, pick]

    def exchange(self, sel: list[int], r: int, deadline: float) -> tuple[list[int], int, bool]:
        """One best-improvement step of drop / move-revisit / swap; (sel, r, improved)."""
        cost = self.costs()
        n = len(self.d.poses)
        cur = self.score(np.array(self.ratio_of(self.counts(sel, r)).max()),
                         np.array(self.total(sel, r, cost)))
        best: tuple[float, list[int], int] | None = None

        def consider(s: float, new_sel: list[int], new_r: int) -> None:
            nonlocal best
            if s < cur - 1e-9 and (best is None or s < best[0]):
                best = (s, new_sel, new_r)

        for i in range(len(sel)):  # drop pose i
            if len(sel) > 2:
                ns = sel[:i] + sel[i + 1:]
                nr = 0 if i == r else (r - (i < r))
                w = self.counts(ns, nr)
                consider(float(self.score(self.ratio_of(w).max(),
                                          np.array(self.total(ns, nr, cost)))), ns, nr)
            if i != r:  # revisit pose i instead
                consider(float(self.score(
                    self.ratio_of(self.counts(sel, i)).max(),
                    np.array(self.total(sel, i, cost)))), sel, i)
        avail = np.flatnonzero(~self.excluded & (self.counts(sel, r) == 0))
        for i in range(len(sel)):  # swap pose i for any candidate
            if time.thread_time() > deadline or avail.size == 0:
                break
            mult = 2.0 if i == r else 1.0
            base = self.counts(sel, r)
            base[sel[i]] -= mult
            rat = self.ratio_plus(base, avail, mult).max(axis=1)
            tot = self.total(sel, r, cost) + mult * (cost[avail] - cost[sel[i]])
            sc = self.score(rat, tot)
            for j in np.argsort(settled(sc), kind="stable")[:n]:
                if sc[j] >= cur - 1e-9 or (best is not None and sc[j] >= best[0]):
                    break
                k = int(avail[j])
                if not self.c.visit(k).ok:  # lazily: only what a better design wants
                    self.excluded[k] = True
                    continue
                if self.c.cost_s(k) != cost[k]:  # built: its exact cost may differ
                    return sel, r, True  # rescore everything with the new calibration
                consider(float(sc[j]), [*sel[:i], k, *sel[i + 1:]], r)
                break
        if best is None:
            return sel, r, False
        return best[1], best[2], True


def optimise(pb: Problem) -> Chosen:
    """Choose and order the poses (see the module docstring)."""
    t0 = time.perf_counter()
    cpu0 = time.thread_time()
    poses = candidate_poses(pb.machine, pb.grid)
    if len(poses) < 2:
        raise ValueError("fewer than two candidate poses within the rotary travel: widen "
                         "candidates.b_range_deg or make the steps finer")
    d = build_design(pb.machine, pb.artefact, poses, pb.links, pb.sigma_um, pb.index_urad)
    cands = Candidates(pb.machine, pb.machine_file, pb.artefact, pb.probing, pb.two_speed,
                       poses, d.centres_mm)
    s = _Search(pb, d, cands)
    cands.refuse_table()
    s.excluded |= np.array([not cands.visits[i].ok if i in cands.visits else False
                            for i in range(len(poses))])
    s.excluded[[i for i, _ in pb.refused]] = True
    deadline = cpu0 + DEADLINE_S
    sel: list[int] = []
    r = 0
    stopped = False
    for _ in range(MAX_STEPS):  # deterministic: the deadline is only a guard
        sel = s.greedy(sel, r)
        if len(sel) < 2:
            break
        sel, r, improved = s.exchange(sel, r, deadline)
        stopped = time.thread_time() > deadline
        if not improved or stopped:
            sel = s.greedy(sel, r)
            break
    if len(sel) < 2:
        raise ValueError("no two safe candidate poses fit: the plan cannot identify the links"
                         + (" within the time cap" if pb.max_time_s else ""))
    w = s.counts(sel, r)
    if not np.all(np.isfinite(link_u(d, d.info_of(w), d.meat_of(w)))):
        raise ValueError("no plan that identifies every link fits"
                         + (" within the time cap" if pb.max_time_s else ""))
    val = _validation(s, sel, pb.validate_poses)
    visits = [sel[r], *[x for i, x in enumerate(sel) if i != r], *val]
    roles = ["estimate"] * len(sel) + ["validate"] * len(val)
    order, times = _order(s, visits, [x == "estimate" for x in roles])
    visits = [visits[i] for i in order]
    roles = [roles[i] for i in order]
    c_un = unwrap_c([poses[v][1] for v in visits], pb.machine.axes[pb.machine.rotary_axes[1]]
                    .travel)
    u = link_u(d, d.info_of(w), d.meat_of(w))
    rat = u[s.tidx] / s.tval
    missed = {k: (float(u[pb.links.index(k)]), t) for (k, t), q in
              zip(pb.targets.items(), rat, strict=True) if q > 1.0 + 1e-9}
    excluded = [f"B{poses[i][0]:g} C{poses[i][1]:g}: {cands.visits[i].reason}"
                for i in np.flatnonzero(s.excluded) if i in cands.visits
                and not cands.visits[i].ok]
    refused = [f"B{poses[i][0]:g} C{poses[i][1]:g}: {why}" for i, why in pb.refused]
    return Chosen([(poses[v][0], c) for v, c in zip(visits, c_un, strict=True)], roles, visits,
                  {k: float(x) for k, x in zip(pb.links, u, strict=True)}, missed,
                  times[-1] * 3600.0, cands.builds, excluded, time.perf_counter() - t0, d,
                  [t for t, role in zip(times[:-1], [*roles, roles[0]], strict=True)
                   if role == "estimate"], stopped, refused)


def _validation(s: _Search, sel: list[int], n: int) -> list[int]:
    """``n`` held-out poses far (in B and C) from the chosen ones and from each other, the
    cheaper first among equals: predicted on poses the estimate did not use (thesis annex B)."""
    poses = np.array(s.d.poses)
    out: list[int] = []
    cost = s.costs()
    while len(out) < n:
        used = poses[sel + out]
        dc = np.abs((poses[:, None, 1] - used[None, :, 1] + 180.0) % 360.0 - 180.0)
        dist = np.hypot(poses[:, None, 0] - used[None, :, 0], dc).min(axis=1)
        dist = np.where(s.excluded | np.isin(np.arange(len(poses)), sel + out), -np.inf, dist)
        if not np.isfinite(dist.max()):
            break
        k = int(np.argmax(dist - 1e-3 * cost))
        if s.c.visit(k).ok:
            out.append(k)
        else:
            s.excluded[k] = True
    return out


def _order(s: _Search, visits: list[int], estimate: list[bool]
           ) -> tuple[list[int], list[float]]:
    """Run order of ``visits`` (the first is the revisited pose; ``estimate``: not held out)
    and each visit's mid time in hours (the revisit last), then the end of the run."""
    poses = [s.d.poses[v] for v in visits]
    c_un = unwrap_c([p[1] for p in poses],
                    s.pb.machine.axes[s.pb.machine.rotary_axes[1]].travel)
    ps = [(p[0], c) for p, c in zip(poses, c_un, strict=True)]
    vis = [s.c.visit(v) for v in visits]
    n = len(visits)
    cost = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            if i != j:
                cost[i, j] = s.c.transition_s(ps[i], vis[i], ps[j], vis[j])

    def times(order: list[int]) -> list[float]:
        t, out = 0.0, []
        seq = [*order, order[0]]
        for a, b in itertools.pairwise(seq):
            out.append(t + vis[a].t_in_s / 2)
            t += vis[a].t_in_s + cost[a, b]
        out.append(t + vis[seq[-1]].t_in_s / 2)
        return [x / 3600.0 for x in out] + [(t + vis[seq[-1]].t_in_s) / 3600.0]

    def penalty(order: list[int]) -> float:
        """Worst target ratio with a drift estimated too (estimate visits only): a linear
        drift or a warm-up of τ 10-60 min, whichever costs the links most."""
        seq = [*order, order[0]]
        t = times(order)[:-1]
        keep = [i for i, v in enumerate(seq) if estimate[v]]
        u = drift_u_worst(s.d, [visits[seq[i]] for i in keep], [t[i] for i in keep])
        return float((u[s.tidx] / s.tval).max())

    order = order_tour(cost, c_un, penalty)
    return order, times(order)
