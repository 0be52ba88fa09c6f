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
    degrees,
    operator_page,
    values,
)

if TYPE_CHECKING:
    from identification.compensation import ParamChange


def render(spec: ControllerKinematics, changes: Sequence[ParamChange], *, run_id: str,
           machine: str, rollback: bool = False) -> CompensationOutput:
    """The operator's page (``rollback``: the old values back)."""
    return operator_page(
        values(spec, changes, orientation=degrees, rollback=rollback), run_id=run_id,
        machine=machine, rollback=rollback, address_label="row/col", with_unit=True,
        instructions=["Enter in the active kinematics table (machine-parameter editor, code "
                      "number),",
                      "then check with cycle 451 in measure mode (cycle 451 owns the optimise "
                      "write)."])


__all__ = ["render"]
