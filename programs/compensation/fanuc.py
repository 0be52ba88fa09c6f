"""Fanuc: a reviewed parameter program (G10 L52 programmable parameter input, macro variables).

A parameter address (``19700``) is written as ``G10 L52`` / ``N<param> R<value>`` / ``G11``:
a real-type parameter in mm (pivot) or deg (orientation: the held link's angle, right-hand
rule about the error's axis) with the decimal point — the control rounds it to its least input
increment. A macro-variable address (``#500``, e.g. what a shift-start macro adds to the work
offset) is written ``#500=<value>``. Each write follows a comment with its old and new value.
Parameter writing needs PWE = 1 on the control: the program is for review, then run by hand.
Axis-type parameters (``N<param> P<axis> R<value>``) are not addressed: name a real-type one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from contracts.controller_kinematics import ControllerKinematics
from programs.compensation.common import (
    CompensationOutput,
    comment,
    degrees,
    describe,
    filename,
    listing,
    title,
    values,
)

if TYPE_CHECKING:
    from identification.compensation import ParamChange

PROGRAM_NUMBER = 9990


def render(spec: ControllerKinematics, changes: Sequence[ParamChange], *, run_id: str,
           machine: str, rollback: bool = False) -> CompensationOutput:
    """The parameter program (``rollback``: the old values back)."""
    vals = values(spec, changes, orientation=degrees, rollback=rollback)
    lines = ["%", f"O{PROGRAM_NUMBER} ({comment(title(run_id, machine, rollback))})".upper(),
             "(REVIEW BEFORE RUNNING: WRITES KINEMATIC PARAMETERS, NEEDS PWE=1)"]
    for r in listing(vals):  # the strings the person confirmed
        where = f"VAR {r.address[1:]}" if r.address.startswith("#") else f"PARAM {r.address}"
        lines.append(f"({comment(f'{where} {describe(r)}').upper()})")
        if r.address.startswith("#"):
            lines.append(f"{r.address}={r.written}")
        else:
            lines += ["G10 L52", f"N{r.address} R{r.written}", "G11"]
    lines += ["M30", "%"]
    return CompensationOutput("\n".join(lines) + "\n", filename(run_id, machine, "nc", rollback),
                              vals)


__all__ = ["PROGRAM_NUMBER", "render"]
