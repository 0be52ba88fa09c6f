"""Which map terms the placements determine, derived numerically (METHOD.md §2, §7), and what
absorbs the others.

The Jacobian at the nominal machine of every placement (calibrated distances as rows) is taken
with its columns scaled to unit norm, kept greedily in a fixed priority order — setup (probe,
every placement's balls), then the location errors (``Machine.location_error_names`` order, as
``identification.identifiability``), then the map terms in ``terms.candidate_terms`` order — a
column is kept when its part orthogonal to the kept ones exceeds ``INDEPENDENT`` of its norm
(Gram-Schmidt, twice for stability). A dropped column is named with the kept columns that carry
it; three absorptions are said in words: the isotropic scale (no calibrated distance), an
angular error that moves the tip only as a straightness with this one stylus (the map holds
their sum, for this stylus), a linear straightness that is a squareness (a link).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.identifiability import explain_absorption
from identification.kinematics import Machine
from identification.linmap.problem import JointLayout, MapError, Placement, evaluate
from identification.linmap.terms import MapBasis, MapTerm
from identification.model import Centres

INDEPENDENT = 1e-6  # relative norm of a unit column's part outside the kept span


@dataclass(frozen=True)
class Observability:
    """The link set and map terms kept, and what was dropped with what absorbs it."""

    links: tuple[str, ...]
    terms: tuple[MapTerm, ...]
    dropped_links: dict[str, str]
    dropped_terms: dict[str, str]
    scale_observable: bool
    # the weakest kept term: its relative independent part (1: orthogonal to everything kept)
    independence: dict[str, float] = field(default_factory=dict)
    candidates: tuple[str, ...] = ()  # every term tried (up to the degree cap)

    def statement(self, machine: Machine, max_degree: dict[str, int] | None = None
                  ) -> dict[str, str]:
        """Named unobservable directions → what absorbs them (for reports and the JSON): the
        isotropic scale, the links, then the map terms (up to ``max_degree`` per axis, all
        when None), a component whose every degree is dropped named once."""
        out: dict[str, str] = {}
        if not self.scale_observable:
            out["isotropic_scale"] = ("not observable without a calibrated distance between two "
                                      "balls: the ball setups absorb it (the artefact's size); "
                                      "the map is a volumetric distortion, its positioning "
                                      "slopes relative to one another")
        out.update(self.dropped_links)
        tried: dict[str, list[str]] = {}
        for name in self.candidates:
            tried.setdefault(name.split("_P")[0], []).append(name)
        for comp, names in tried.items():
            top = None if max_degree is None else max(max_degree.get(comp[2], 0), 1)
            names = [n for n in names if top is None or int(n.split("_P")[1]) <= top]
            gone = [n for n in names if n in self.dropped_terms]
            if gone and len(gone) == len(names) and len(names) > 1:
                out[comp] = f"every degree ({len(names)}): {self.dropped_terms[gone[0]]}"
            else:
                out.update({n: self.dropped_terms[n] for n in gone})
        return out


class _Span:
    """An orthonormal basis grown one column at a time (modified Gram-Schmidt, twice)."""

    def __init__(self, rows: int) -> None:
        self.q = np.zeros((rows, 0))

    def residual(self, col: np.ndarray) -> np.ndarray:
        r = col.copy()
        for _ in range(2):
            r -= self.q @ (self.q.T @ r)
        return r

    def add(self, r: np.ndarray) -> None:
        self.q = np.hstack([self.q, (r / np.linalg.norm(r))[:, None]])


def _stacked(machine: Machine, placements: Sequence[Placement], layout: JointLayout
             ) -> np.ndarray:
    """(rows, P) the Jacobian at the nominal machine: centres (µm per unit, σ = 1 µm) and the
    calibrated distances weighted by their stated σ (rows comparable to a 1 µm centre)."""
    nominal = []
    for pl in placements:
        c = pl.centres
        nominal.append(Placement(pl.name, pl.artefact,
                                 Centres(c.pose, c.ball, c.b_deg, c.c_deg, c.xyz_mm.copy())))
    ev = evaluate(machine, nominal, layout, np.zeros(layout.size), jacobian=True)
    assert ev.jac is not None
    rows = [j.reshape(-1, layout.size) for j in ev.jac]
    if len(ev.dist):
        rows.append(ev.dist_jac / (ev.dist_std[:, None] * 1e3))
    return np.vstack(rows)


def _words(term: MapTerm, absorbers: str, machine: Machine) -> str:
    names = [a.strip() for a in absorbers.split("+")]
    links = set(machine.location_error_names())
    own = [n for n in names if n.startswith("E") and n[2:3] == term.axis and "_P" in n]
    tool_side = term.axis in machine.tool_chain
    if term.rotation and tool_side and absorbers.startswith("nothing"):
        return (f"with one stylus an angular error of {term.axis} (the tool side) moves the tip "
                f"only as a straightness of {term.axis} does (the tool tip is {term.axis}'s "
                f"reference point in this machine file): the translations of {term.axis} hold "
                "their sum, valid for this stylus")
    if term.rotation and own and all(not MapTerm(n[2], "XYZABC".index(n[1]), 1).rotation
                                     for n in own):
        side = "tool" if tool_side else "workpiece"
        return (f"{absorbers}: with one stylus length an angular error of {term.axis} (the "
                f"{side} side) moves the tip exactly as a straightness or positioning error of "
                f"{term.axis}; the map holds their sum, valid for this stylus")
    if term.degree == 1 and not term.rotation and any(n in links for n in names):
        return f"{absorbers}: a linear straightness is a squareness, a link error"
    return absorbers


def observable_terms(machine: Machine, placements: Sequence[Placement],
                     candidates: Sequence[MapTerm], ranges_mm: dict[str, tuple[float, float]]
                     ) -> Observability:
    """Keep the links and map terms the placements separate from the setup (module doc)."""
    all_links = tuple(machine.location_error_names())
    basis = MapBasis(ranges_mm, tuple(candidates))
    layout = JointLayout(all_links, basis, tuple(len(p.artefact.balls) for p in placements))
    j = _stacked(machine, placements, layout)
    names = layout.names(placements)
    norms = np.linalg.norm(j, axis=0)
    jn = j / np.where(norms > 0, norms, 1.0)
    setup = list(range(layout.tip_slice.start, layout.size))
    span = _Span(j.shape[0])
    kept: list[int] = []
    for i in setup:
        r = span.residual(jn[:, i])
        if norms[i] == 0 or np.linalg.norm(r) < INDEPENDENT:
            raise MapError(f"the setup errors alone are not identifiable from these "
                             f"placements ({names[i]}); need at least two distinct indexations "
                             "per placement")
        span.add(r)
        kept.append(i)
    dropped: dict[int, str] = {}
    independence: dict[str, float] = {}
    order = list(range(len(all_links))) + list(range(layout.map_slice.start,
                                                     layout.map_slice.stop))
    for i in order:
        r = span.residual(jn[:, i]) if norms[i] > 0 else np.zeros(j.shape[0])
        rel = float(np.linalg.norm(r))
        if norms[i] > 0 and rel >= INDEPENDENT:
            span.add(r)
            kept.append(i)
            if i >= layout.map_slice.start:
                independence[names[i]] = rel
        else:
            dropped[i] = explain_absorption(j[:, i], j[:, kept], [names[k] for k in kept])
    links = tuple(all_links[i] for i in sorted(kept) if i < len(all_links))
    m0, m1 = layout.map_slice.start, layout.map_slice.stop
    terms = tuple(candidates[i - m0] for i in sorted(kept) if m0 <= i < m1)
    dropped_links = {all_links[i]: by for i, by in dropped.items() if i < len(all_links)}
    scale_obs = _scale_observable(machine, placements, j, kept, names, layout)
    dropped_terms = {}
    for i, by in dropped.items():
        if i < m0:
            continue
        t = candidates[i - m0]
        if not scale_obs and t.slot == "XYZ".index(t.axis) and t.degree == 1:
            by = (f"{by}: the isotropic scale (no calibrated distance): the positioning "
                  f"slopes of the other axes are given relative to {t.axis}'s")
        else:
            by = _words(t, by, machine)
        dropped_terms[t.name] = by
    return Observability(links, terms, dropped_links, dropped_terms, scale_obs, independence,
                         tuple(t.name for t in candidates))


def predicted_std(machine: Machine, placements: Sequence[Placement], obs: Observability,
                  ranges_mm: dict[str, tuple[float, float]], sigma_um: float = 1.0
                  ) -> dict[str, float]:
    """The standard uncertainty (µm or µrad) of each kept map term from these placements at
    the nominal machine, every centre coordinate with noise ``sigma_um`` and no prior: the
    inverse information of the kept links, terms and setups (what a plan is judged by before
    it runs; the fit's own u adds the a-posteriori σ and the prior)."""
    basis = MapBasis(ranges_mm, tuple(obs.terms))
    layout = JointLayout(obs.links, basis, tuple(len(p.artefact.balls) for p in placements))
    j = _stacked(machine, placements, layout)
    cov = np.linalg.pinv(j.T @ j) * sigma_um**2
    s = layout.map_slice
    return {t.name: float(np.sqrt(max(cov[i, i], 0.0)) * t.to_si)
            for t, i in zip(obs.terms, range(s.start, s.stop), strict=True)}


def _scale_observable(machine: Machine, placements: Sequence[Placement], j: np.ndarray,
                      kept: list[int], names: list[str], layout: JointLayout) -> bool:
    """Is the isotropic scale of the linear axes separate from the setup (and links)? Only a
    calibrated distance makes it so (METHOD.md §3): tested, not assumed."""
    if not any(pl.artefact.distances for pl in placements):
        return False
    base = [k for k in kept if k < layout.map_slice.start or k >= layout.tip_slice.start]
    span = _Span(j.shape[0])
    jn = j / np.where(np.linalg.norm(j, axis=0) > 0, np.linalg.norm(j, axis=0), 1.0)
    for k in base:
        r = span.residual(jn[:, k])
        if np.linalg.norm(r) >= INDEPENDENT:
            span.add(r)
    # the scale as three positioning slopes in mm per mm of joint value: s · q on every axis
    col = np.zeros(j.shape[0])
    for t_name in ("EXX_P1", "EYY_P1", "EZZ_P1"):
        if t_name in names:
            col += j[:, names.index(t_name)] * _half(layout.basis, t_name[2])
    if not np.any(col):
        return False
    r = span.residual(col / np.linalg.norm(col))
    return bool(np.linalg.norm(r) >= INDEPENDENT)


def _half(basis: MapBasis, axis: str) -> float:
    lo, hi = basis.ranges_mm[axis]
    return (hi - lo) / 2.0
