"""Haas: the settings to enter by hand (Haas has no program write of settings), page and program.

``render`` gives the operator's page (setting number, old, new, in mm: the control must be in
metric, Setting 9 = MM); ``program`` the same as a program of comments only, to load on the
control and read next to the settings page. Haas keeps no orientation setting: the section
refuses orientation parameters for this family.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from contracts.controller_kinematics import ControllerKinematics
from programs.compensation.common import (
    CompensationOutput,
    comment,
    filename,
    listing,
    operator_page,
    title,
    values,
)

if TYPE_CHECKING:
    from identification.compensation import ParamChange

PROGRAM_NUMBER = "O09990"


def render(spec: ControllerKinematics, changes: Sequence[ParamChange], *, run_id: str,
           machine: str, rollback: bool = False) -> CompensationOutput:
    """The operator's page: every setting to enter, old and new (``rollback``: old back)."""
    return operator_page(
        values(spec, changes, rollback=rollback), run_id=run_id, machine=machine,
        rollback=rollback, address_label="setting", with_unit=False,
        instructions=["Enter on the control: SETTINGS, the number, the new value, WRITE/ENTER.",
                      "Values in mm: the control must be in metric (Setting 9 = MM)."])


def program(spec: ControllerKinematics, changes: Sequence[ParamChange], *, run_id: str,
            machine: str, rollback: bool = False) -> CompensationOutput:
    """The same as a program of comments (it changes nothing when run)."""
    vals = values(spec, changes, rollback=rollback)
    lines = ["%", f"{PROGRAM_NUMBER} ({comment(title(run_id, machine, rollback)).upper()})",
             "(ENTER THESE SETTINGS BY HAND, VALUES IN MM)"]
    for r in listing(vals):
        text = f"SETTING {r.address} {r.name} OLD {r.was} NEW {r.written}"
        lines.append(f"({comment(text).upper()})")
    lines += ["M30", "%"]
    return CompensationOutput("\n".join(lines) + "\n", filename(run_id, machine, "nc", rollback),
                              vals)


__all__ = ["PROGRAM_NUMBER", "program", "render"]
