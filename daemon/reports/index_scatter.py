"""The rotary axes' indexing repeatability behind a run's link u, as every screen prints it."""

# The analysis JSON's estimation.index_scatter (identify.index_scatter) in
# one text per axis, shown by the HTML report, its PDF and JSON, the HMI's verdict card and
# its run API, so that one run tells one story (defined once, here).

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from daemon.analysis.result import Analysis, IndexScatter
from identification.estimate_scatter import STATED_TAG
from identification.visit_scatter import LR_ALPHA

TITLE = "Indexing repeatability of the rotary axes"
DEFINITION = ("µrad 1σ per indexation of the rotary axis: this run's restricted-maximum-"
              "likelihood estimate from its visits ± its standard uncertainty, the machine "
              "file's stated value (rotary_repeatability_urad, a Type B input) and the one the "
              "link uncertainties use; a stated value is overridden when the run's estimate "
              f"exceeds it at p < {LR_ALPHA:g} (one-sided likelihood-ratio test)")
NONE = ("Indexing repeatability: not estimated for this run (fewer than 4 visits or fewer "
        "than two rotary axes, or an analysis written before it was recorded): the link "
        "uncertainties hold no index component")


def _um(v: float | None) -> str:
    return "—" if v is None else f"{v:.1f}"


def axis_text(x: IndexScatter) -> str:
    """"B indexing repeatability: 3.1 ± 1.4 µrad estimated from 8 visits, machine file
    states 4 µrad, used: stated" (with the test when the stated value was overridden)."""
    est = _um(x.estimated_urad) + ("" if x.std_urad is None else f" ± {x.std_urad:.1f}")
    seen = f" from {x.visits} visits" if x.visits is not None else ""
    stated = "none" if x.stated_urad is None else f"{x.stated_urad:g} µrad"
    text = (f"{x.axis} indexing repeatability: {est} µrad estimated{seen}, machine file states "
            f"{stated}, used: {x.used}")
    if x.stated_urad is not None and x.used == "estimated" and x.p_stated is not None:
        text += (f" (the stated {x.stated_urad:g} µrad overridden: one-sided likelihood-ratio "
                 f"test p = {x.p_stated:.2g} < {LR_ALPHA:g})")
    return text


def index_scatter_lines(analysis: Analysis) -> list[str]:
    """One line per rotary axis, then the warning of each overridden stated value; one line
    saying why there is nothing when the analysis holds no index scatter."""
    est = analysis.estimation  # None in an analysis without an estimation block
    return lines_of(est.index_scatter if est is not None else None, analysis.warnings)


def lines_of(axes: Sequence[IndexScatter] | None, warnings: Sequence[str]) -> list[str]:
    """``index_scatter_lines`` of the estimation's entries and the analysis' warnings."""
    if not axes:
        return [NONE]
    lines = [axis_text(x) for x in axes]
    for x in axes:
        if x.stated_urad is not None and x.used == "estimated":
            lines += [f"Warning: {w}" for w in warnings
                      if w.startswith(f"{x.axis} indexing repeatability") and STATED_TAG in w]
    return lines


def index_scatter_text(data: Any) -> str:
    """The lines of an analysis JSON's parts as a store holds them (the fleet page's cell):
    ``{"index_scatter": estimation.index_scatter, "warnings": …}``; "" without an analysis.
    A row of another version costs the cell, never the page."""
    if not isinstance(data, Mapping):
        return ""
    try:
        axes = [IndexScatter.from_json(x) for x in data.get("index_scatter") or ()]
        warnings = [str(w) for w in data.get("warnings") or ()]
        return "; ".join(lines_of(axes, warnings))
    except (TypeError, ValueError, KeyError, AttributeError):
        return ""


def index_scatter_doc(analysis: Analysis) -> dict[str, Any]:
    """The section as the report's JSON and the HMI's run API carry it."""
    return {"title": TITLE, "definition": DEFINITION, "lines": index_scatter_lines(analysis)}
