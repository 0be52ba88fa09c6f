"""Which controller changes are worth writing: the rule, each change's effect, the distortion
left by a subset of the changes, and numbers worded so that two compared figures differ."""

# The rule (README "Compensation write-back"). A change of a controller value is proposed
# only when all of these hold:
#   1. observable: the data can see it (the setup does not absorb it);
#   2. significant: |Δ| > U, its expanded uncertainty at the judge's coverage (k·u, Student t
#      on the estimate's dof, ``identification.uncertainty.expanded_k``);
#   3. it matters: its own effect, the largest displacement of a probed ball centre it makes
#      at the run's poses (setup projected out, as the plan's distortions), is at least
#      ``min_effect_um`` (the machine file's guards.min_effect_um, default 2 µm: about twice
#      the verification's own resolution, k·u_c ≈ 1.2 µm on the demo machine — a smaller
#      change could not be told from the probing noise by the run that verifies it).
# The changes passing 1-3 are proposed together only when
#   4. they lower the largest link-caused distortion at the probed poses by at least
#      ``min_effect_um`` and raise neither its RMS nor its max (a rise of more than
#      ``WORSE_TOL_UM`` refuses them as making the machine worse);
# else nothing is proposed and the panel says why, with the figures. The daemon adds
#   5. a run that verifies an applied compensation and PASSed proposes nothing: that
#      compensation is done; changing a conforming machine on the next estimate would only
#      move it by that estimate's noise (``daemon.compensation.propose``).

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np


class ParamChange(Protocol):
    """A change as ``identification.compensation.ParamChange`` carries it (the rule reads
    only these; a protocol, so that this module does not import the planner that uses it)."""

    name: str
    kind: str
    delta: float
    u_expanded: float
    observable: bool
    note: str


class CompensationPlan(Protocol):
    """What the rule reads of ``identification.compensation.CompensationPlan``."""

    changes: list
    distortion_before_um: tuple[float, float]
    distortion_after_um: tuple[float, float]

    def effect_um(self, name: str) -> float | None: ...

    def after_um(self, names: list[str]) -> tuple[float, float]: ...

MIN_EFFECT_MM = 0.002
"""Default of guards.min_effect_um (2 µm): rules 3 and 4 above."""
WORSE_TOL_UM = 0.01
"""Predicted after above before by more than this (µm, RMS or max) is "worse": refused.
Closer than that the two are the same figure (and the gain is under rule 4's threshold)."""


def norms_um(d: np.ndarray) -> tuple[float, float]:
    """(RMS, max) of the lengths of displacement vectors ``d`` (mm, any shape (…, 3)), µm."""
    n = np.linalg.norm(np.asarray(d, float).reshape(-1, 3), axis=1) * 1e3
    return (float(np.sqrt(np.mean(n**2))), float(n.max())) if n.size else (0.0, 0.0)


def effect_um(disp: np.ndarray | None) -> float | None:
    """A change's effect: the largest displacement of a probed centre it makes (µm); None
    when the plan does not carry its displacements (a plan built by hand)."""
    return None if disp is None else norms_um(disp)[1]


def after_um(link_disp: np.ndarray | None, change_disp: Mapping[str, np.ndarray],
             names: Iterable[str], fallback: tuple[float, float]) -> tuple[float, float]:
    """(RMS, max) of the link-caused distortion left once the changes ``names`` are written:
    the link-caused displacements minus those the named changes reproduce; ``fallback`` when
    the plan carries no displacements."""
    if link_disp is None:
        return fallback
    left = np.array(link_disp, float)
    for n in names:
        left = left - change_disp[n]
    return norms_um(left)


def pair(a: float, b: float, decimals: int = 1, most: int = 4) -> tuple[str, str]:
    """``a`` and ``b`` with the fewest decimals (from ``decimals``, at most ``most``) that
    tell them apart, never ``-0.0``: "4.73" and "4.71", not "4.7" and "4.7"."""
    for d in range(decimals, most + 1):
        sa, sb = plain(a, d), plain(b, d)
        if sa != sb:
            return sa, sb
    return plain(a, most), plain(b, most)


def plain(v: float, decimals: int = 1, sign: bool = False) -> str:
    """``v`` with ``decimals`` decimals, a zero never negative ("-0.00" is "0.00")."""
    s = f"{v:+.{decimals}f}" if sign else f"{v:.{decimals}f}"
    if float(s) == 0.0:
        s = f"{0.0:.{decimals}f}"
    return s


@dataclass(frozen=True)
class Guards:
    """Limits of one compensation (KinematicsOpt's 0.05 mm per value) and the worth rule's
    threshold (``identification.worth``)."""

    max_change_mm: float = 0.05  # per pivot value
    max_change_rad: float = 100e-6  # per orientation value
    max_total_mm: float = 0.1  # sum of |pivot changes|
    min_effect_mm: float = MIN_EFFECT_MM  # rules 3 and 4 of the worth rule


@dataclass(frozen=True)
class GuardResult:
    """What to apply. When ``refused`` is not empty nothing is applied: ``accepted`` is empty
    and ``proposed`` keeps the changes that passed the per-change rules. ``after_um``: the
    link-caused distortion (RMS, max) predicted once ``accepted`` is written (before, when
    nothing is); ``not_worth``: why nothing is proposed although changes passed rules 1-3."""

    accepted: list[ParamChange]
    skipped: list[tuple[ParamChange, str]]
    refused: list[str]
    proposed: list[ParamChange] = dataclasses.field(default_factory=list)
    after_um: tuple[float, float] | None = None
    not_worth: str = ""

    @property
    def ok(self) -> bool:
        return not self.refused


def _size(ch: ParamChange, value: float, sign: bool = True) -> str:
    if ch.kind == "pivot":
        return f"{plain(value * 1e3, 1, sign)} µm"
    return f"{plain(value * 1e6, 1, sign)} µrad"


def _sizes(ch: ParamChange, a: float, b: float) -> tuple[str, str]:
    """|a| and |b| in µm / µrad with the decimals that tell them apart."""
    f, unit = (1e3, "µm") if ch.kind == "pivot" else (1e6, "µrad")
    x, y = pair(abs(a) * f, abs(b) * f, 2)
    return f"{x} {unit}", f"{y} {unit}"


def worse_after(plan: CompensationPlan, after: tuple[float, float] | None = None) -> list[str]:
    """"predicted after compensation" must never exceed "before" silently. The
    changes reproduce the projection of the link-caused displacements on what they can hold;
    the remainder can still be larger (RMS or max) when the held part is ill-conditioned or
    clipped, and such changes would make the machine worse: refused, with both figures worded
    so that they differ. ``after``: of the changes proposed (default: the plan's)."""
    after = plan.distortion_after_um if after is None else after
    out = []
    for i, what in enumerate(("RMS", "max")):
        before, now = plan.distortion_before_um[i], after[i]
        if now > before + WORSE_TOL_UM:
            a, b = pair(now, before)
            out.append(f"predicted after compensation {what} {a} µm exceeds the link-caused "
                       f"distortion {what} {b} µm before it: the changes would make the "
                       "machine worse")
    return out


def check_guards(plan: CompensationPlan, guards: Guards) -> GuardResult:
    """The worth rule (``identification.worth``: observable, over its own expanded
    uncertainty, an effect of at least ``min_effect_mm``; together a gain of at least that
    on the max link-caused distortion, never worse), then the limits: the whole compensation
    is refused when an accepted value or the pivot total is over its limit."""
    proposed: list[ParamChange] = []
    skipped: list[tuple[ParamChange, str]] = []
    floor_um = guards.min_effect_mm * 1e3
    for ch in plan.changes:
        effect = plan.effect_um(ch.name)
        if not ch.observable:
            skipped.append((ch, f"not observable: {ch.note}" if ch.note else "not observable"))
        elif abs(ch.delta) <= ch.u_expanded:
            d, u = _sizes(ch, ch.delta, ch.u_expanded)
            skipped.append((ch, f"smaller than its own expanded uncertainty (|Δ| {d} <= U "
                                f"{u})"))
        elif effect is not None and effect < floor_um:
            e, f = pair(effect, floor_um, 1, 3)
            skipped.append((ch, f"moves the probed ball centres by {e} µm at most, under the "
                                f"{f} µm a change must move them to be worth writing "
                                "(guards.min_effect_um)"))
        else:
            proposed.append(ch)
    refused: list[str] = []
    for ch in proposed:
        limit = guards.max_change_mm if ch.kind == "pivot" else guards.max_change_rad
        if abs(ch.delta) > limit:
            refused.append(f"{ch.name}: change {_size(ch, ch.delta)} is over the limit "
                           f"{_size(ch, limit, sign=False)}")
    total = sum(abs(ch.delta) for ch in proposed if ch.kind == "pivot")
    if total > guards.max_total_mm:
        refused.append(f"total of the pivot changes {total * 1e3:.1f} µm is over the limit "
                       f"{guards.max_total_mm * 1e3:.1f} µm")
    after = plan.after_um([ch.name for ch in proposed])
    refused += worse_after(plan, after)
    if refused:
        skipped += [(ch, "refused with the whole compensation") for ch in proposed]
        return GuardResult([], skipped, refused, proposed, plan.distortion_before_um)
    before = plan.distortion_before_um
    gain = before[1] - after[1]
    if proposed and gain < floor_um:
        b, a = pair(before[1], after[1])
        if gain > 0:
            g, f = pair(gain, floor_um, 2)
            how = f"would lower the link-caused distortion max by {g} µm only ({b} → {a} µm)"
        else:
            f = plain(floor_um, 1)
            how = f"would not lower the link-caused distortion max ({b} → {a} µm)"
        why = (f"together they {how}, under the {f} µm a compensation must gain to be worth "
               "writing (guards.min_effect_um)")
        skipped += [(ch, why) for ch in proposed]
        return GuardResult([], skipped, [], [], before, why)
    return GuardResult(list(proposed), skipped, [], proposed, after)


__all__ = ["MIN_EFFECT_MM", "WORSE_TOL_UM", "GuardResult", "Guards", "after_um", "check_guards",
           "effect_um", "norms_um", "pair", "plain", "worse_after"]
