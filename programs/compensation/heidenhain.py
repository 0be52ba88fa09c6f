"""Heidenhain: the kinematics-table values to enter (cycle 451 owns the write on this control).

A text page for the operator: kinematics-table row/column, old, new. Pivots (columns X, Y, Z)
in mm; orientations (columns SPA, SPB, SPC) as the held link's angle in degrees, right-hand rule
about the error's axis (the table's spatial angle of the transformation before the axis).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from contracts.controller_kinematics import ControllerKinematics
from programs.compensation.common import (
    CompensationOutput,
    comment,
    degrees,
    filename,
    fmt_value,
    title,
    values,
)

if TYPE_CHECKING:
    from identification.compensation import ParamChange


def render(spec: ControllerKinematics, changes: Sequence[ParamChange], *, run_id: str,
           machine: str, rollback: bool = False) -> CompensationOutput:
    """The operator's page (``rollback``: the old values back)."""
    vals = values(spec, changes, orientation=degrees, rollback=rollback)
    lines = [comment(title(run_id, machine, rollback)),
             "Enter in the active kinematics table (machine-parameter editor, code number),",
             "then check with cycle 451 in measure mode (cycle 451 owns the optimise write).",
             "",
             f"{'row/col':>8}  {'name':<24} {'old':>16} {'new':>16}  unit"]
    for v in vals:
        lines.append(f"{v.address:>8}  {v.name:<24} {fmt_value(v.old, v.unit):>16} "
                     f"{fmt_value(v.new, v.unit):>16}  {v.unit}")
    return CompensationOutput("\n".join(lines) + "\n", filename(run_id, machine, "txt", rollback),
                              vals)


__all__ = ["render"]
