"""The floor the gap is judged against credits visit scatter only with the visits' signature.

The decision rule between "scatter" and "structure" (README, gap diagnosis):

1. The twin's residuals — every group, training and held-out — are tested first for structure
   along X, Y and Z (``structure.test_structure``), against the run's visit model.
2. Structure found — in the twin's residuals, or with the effects the components are
   estimated with held fixed: it is located (axis, where, size, scale) and reported; the centre
   scatter per ball visit, which cannot tell a pattern along an axis from random scatter, is
   *not* credited, and the rigid index components are estimated again with the located shape
   held fixed (``structure_shape.Shape.columns``; with the effects alone where they remove it)
   so that they take up only what moves a visit rigidly. The floor is then the trigger noise
   plus the rigid index scatter, never more — also for a library effect the diagnosis selects:
   it is named only when its held-out gap comes down to that floor (``after_selection``).
3. No structure in the twin's residuals: they are not a function of any axis' position; the
   centre scatter per ball visit is credited as the REML estimate gives it (the probe's centre
   repeatability, thesis §3.4).

Once the twin's residuals show structure, no later pass credits the centre scatter again: a
library effect that removes only part of a pitch error or a bump leaves the rest to a
component that would take it up as random scatter, and the floor would rise to meet the gap
it leaves (a bump read as a straightness of X, its floor 1.5× the trigger
noise). The floor's parts (``floor_parts``) say in µm how much is trigger noise and how much
visit scatter.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from identification.gap.attribute import ALPHA as GAP_ALPHA
from identification.gap.data import Groups
from identification.gap.linear import Problem
from identification.gap.scatter import VisitScatter, apply, estimate_scatter
from identification.gap.structure import AXES, Structure, test_structure


@dataclass
class StructureFinding:
    """The structure tests of one pass of the diagnosis."""

    twin: Structure | None  # the twin's residuals (the known effects and a step fitted)
    floor: Structure | None  # … with the effects the components are estimated with
    selected: Structure | None = None  # … with the effects the attribution selected
    p_after: float = 1.0  # the held-out gap left by the selected effects (F-test)

    @property
    def found(self) -> bool:
        return self.twin is not None and self.twin.found

    @property
    def unexplained(self) -> bool:
        """The twin showed structure and the selected effects do not remove it: structure
        is left with them fitted (every parameter of theirs), or their held-out gap stays
        significantly above the floor, which credits no centre scatter while it is found."""
        if not self.found:
            return False
        last = self.selected or self.floor or self.twin
        return last.found or self.p_after < GAP_ALPHA

    def as_dict(self) -> dict | None:
        if self.twin is None:
            return None
        out = self.twin.as_dict()
        for key, s in (("with_scatter_effects", self.floor), ("with_selected", self.selected)):
            if s is not None and s is not self.twin:
                out[key] = s.as_dict()
        out["explained_by_selected"] = bool(self.found and self.selected is not None
                                            and not self.unexplained)
        return out


def credit(problem: Problem, groups: Groups, vs: VisitScatter | None, base: np.ndarray,
           with_cols: Sequence[np.ndarray], with_labels: Sequence[str],
           stated_urad: Mapping[str, float] | None, twin: Structure | None = None,
           seen: str = "") -> tuple[VisitScatter | None, StructureFinding]:
    """Test the structure (the twin's ``base`` columns alone — ``twin`` when already done,
    then with the effects the components were estimated with) and, where either finds it,
    estimate the components again without the centre scatter (and with the located shape
    fixed where the effects leave it); the problem's whitening follows (``scatter.apply``).
    ``seen``: the structure an earlier pass found (``seen_structure``) — the centre scatter
    stays withheld even where this pass' components, estimated with the selected effects,
    move the twin's p-value across α."""
    twin = twin or test_structure(problem, groups, vs, base)
    floor = twin if not with_cols else test_structure(
        problem, groups, vs, np.concatenate([base, *with_cols], axis=2), with_labels)
    found = StructureFinding(twin, floor)
    if vs is None or not (seen or any(s is not None and s.found for s in (twin, floor))):
        return vs, found
    extra = list(vs.extra)
    # The located shape stands for the structure while the rigid components are estimated;
    # where the effects fitted with them already remove it, they stand for it themselves
    shape_cols = [] if floor is None or not floor.found else [
        sh.columns(groups.centres.xyz_mm[:, AXES.index(a)], groups.channels)
        for a, sh in floor.shapes().items()]
    last = floor if floor is not None and floor.found else twin
    why = (f"structure along {last.axis} (p = {last.p_value:.2g})"
           if last is not None and last.found else seen)
    held = estimate_scatter(problem, groups, vs.z, vs.axes, extra + shape_cols, stated_urad,
                            withheld=why)
    held.extra, held.labels = extra, vs.labels
    apply(problem, held)
    return held, found


def seen_structure(structure: dict | None) -> str:
    """The withholding reason a first pass' structure finding hands to the later passes."""
    if not structure or not structure.get("found"):
        return ""
    return f"structure along {structure['axis']} (p = {structure['p_value']:.2g}, first pass)"


def after_selection(found: StructureFinding, problem: Problem, groups: Groups,
                    vs: VisitScatter | None, base: np.ndarray, cols: Sequence[np.ndarray],
                    labels: Sequence[str], p_after: float) -> None:
    """Test again with the selected effects fitted too — ``cols``: all their parameters,
    not only the directions the attribution kept visible, whose truncated rest is a smooth
    function of the axis as well — where the twin showed structure; ``p_after``: the F-test
    of the held-out gap they leave."""
    if not found.found or not cols:
        return
    found.p_after = p_after
    found.selected = test_structure(problem, groups, vs, np.concatenate([base, *cols], axis=2),
                                    labels)


def unexplained_message(found: StructureFinding, selected: Sequence, frac: float) -> str:
    """The verdict's sentence for structure no library effect removes."""
    s = found.twin
    where = s.shape.describe(s.axis) if s.shape is not None else "a function of its position"
    also = "".join(f"; also along {a}: {sh.describe(a)}" for a, sh in s.others.items())
    out = (f"structure along {s.axis} that no library effect explains: {where} (p = "
           f"{s.p_value:.2g} over X, Y, Z{also}; ball visits of different indexations follow "
           f"one function of the position — not visit scatter)")
    if selected and found.selected is not None:
        names = ", ".join(c.label for c in selected)
        out += (f"; {names} takes {100 * frac:.0f} % of the held-out excess but leaves it "
                f"(p = {found.selected.p_value:.2g} with it fitted)")
    return out


def floor_parts(vs: VisitScatter | None, floor_um: float) -> dict:
    """How much of the floor is trigger noise and how much visit scatter (RMS per
    observation, µm; the squares add up), and a sentence saying so."""
    parts = vs.parts_um() if vs is not None else {"trigger_um": floor_um, "index_um": 0.0,
                                                  "ball_visit_um": 0.0}
    rigid = np.hypot(parts["trigger_um"], parts["index_um"])
    out = {k: round(v, 4) for k, v in parts.items()}
    held = f" (not credited: {vs.withheld})" if vs is not None and vs.withheld else ""
    out["message"] = (f"floor {floor_um:.3f} µm = trigger noise {parts['trigger_um']:.3f} µm ⊕ "
                      f"rigid index scatter {parts['index_um']:.3f} µm ⊕ centre scatter per "
                      f"ball visit {parts['ball_visit_um']:.3f} µm{held}")
    out["rigid_share"] = round(float(rigid**2 / max(floor_um**2, 1e-30)), 4)
    return out
