"""Siemens 840D: an MPF part program assigning the tool carrier's ``$TC_CARR`` values.

A pivot is an offset-vector component in mm; its ``closing`` component (l4 = −(l2 + l3) for a
swivel table) gets the opposite change so the chain stays closed, changes on one component
adding up. An orientation is a rotary-axis vector component: the nominal unit vector ``v``
(``vector`` of the section, reversed for a table axis) tilted by the held link θ becomes
v + θ·(e_i × v) to first order, so the component the tilt moves is written as ±θ (unit-less,
9 decimals; the nominal components stay). An inclined axis' tilt (about R0·e_i) moves
two or three components: each is written as its nominal value plus its change
(``ControllerParamSpec.vector_values``). Each line carries its old value as a comment.
The carrier is re-selected (TCARR / CYCLE800) after the program for the values to act.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

from contracts.controller_kinematics import ControllerKinematics, ControllerParamSpec
from programs.compensation.common import (
    CompensationOutput,
    comment,
    filename,
    listing,
    title,
    values,
)

if TYPE_CHECKING:
    from identification.compensation import ParamChange


def vector_component(spec: ControllerParamSpec, rad: float) -> list[tuple[str, float, str]]:
    """The axis-vector components holding a tilt of ``rad`` (first order)."""
    return [(address, v, "1") for address, v in spec.vector_values(rad)]


def render(spec: ControllerKinematics, changes: Sequence[ParamChange], *, run_id: str,
           machine: str, rollback: bool = False) -> CompensationOutput:
    """The part program (``rollback``: the old values back)."""
    vals = values(spec, changes, orientation=vector_component, rollback=rollback)
    lines = [f"; {comment(title(run_id, machine, rollback))}",
             "; REVIEW BEFORE RUNNING: WRITES TOOL CARRIER DATA, RESELECT THE CARRIER AFTER"]
    for r in listing(vals):  # the strings the person confirmed
        lines.append(f"{r.address}={r.written} ; {comment(f'{r.name} old {r.was}')}")
    lines.append("M30")
    # a Siemens program name is letters, digits and '_'
    stem = re.sub(r"[^A-Za-z0-9_]", "_", filename(run_id, machine, "mpf", rollback)[:-4])
    return CompensationOutput("\n".join(lines) + "\n", f"{stem}.mpf", vals)


__all__ = ["render", "vector_component"]
