"""What every compensation writer shares: old → new values per address, numbers, safe headers.

A change (``identification.compensation.ParamChange``, mm or rad) is added to the control's
current value (``ControllerParamSpec.value``: mm, or µrad of the held link for an orientation)
and written in the control's unit (``Value.unit``): a Siemens pivot also gives the opposite
change to its ``closing`` vector component, and changes meeting on one address add up.
``rollback=True`` gives the same values the other way round: the control holds ``new`` and gets
``old`` back (the machine file keeps the values from before the compensation).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

from contracts.controller_kinematics import ControllerKinematics, ControllerParamSpec
from contracts.setup_types import SAFE_NAME
from programs.dialects.base import safe_text
from programs.geometry import ProgramError

if TYPE_CHECKING:
    from identification.compensation import ParamChange

RUN_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9-]{0,63}")
"""Run ids as the store makes them (``daemon.store.journal.RUN_ID_PATTERN``, checked by a test)."""
_ADDRESS = re.compile(r"\A[A-Za-z0-9_.$\[\]#/-]{1,48}\Z")  # every family's address charset
MAX_VALUE = 1e6
"""Ceiling on a written value (mm, deg or a vector component): anything larger is a bug."""


class CompensationError(ProgramError):
    """The changes cannot be written for this control (one line naming the value)."""


class Value(NamedTuple):
    """One control value written: its parameter name(s), address, old and new, unit."""

    name: str
    address: str
    old: float
    new: float
    unit: str


class Listed(NamedTuple):
    """One address as the program writes it (or the operator enters it): the strings the
    program holds, so the listing a person confirms and the program cannot disagree."""

    address: str
    written: str  # the new value, exactly as in the program / on the page
    was: str  # the value the control holds before, in the same form
    unit: str  # the control's unit: "mm", "deg", or "1" (a unit-less axis-vector component)
    name: str  # the parameter(s) whose change it is ("b-x+c-x" when two meet on one address)

    def text(self) -> str:
        """``$TC_CARR10[1] = -0.000026670  (was 0.000000000; axis-vector component; c-tilt-b)``"""
        unit = UNIT_TEXT.get(self.unit, self.unit)
        return f"{self.address} = {self.written}  (was {self.was}; {unit}; {self.name})"


UNIT_TEXT = {"mm": "mm", "deg": "deg", "1": "axis-vector component, no unit"}
"""How a listing names each control unit."""


def listing(vals: Sequence[Value]) -> list[Listed]:
    """Every address written, its new and old value as text: the one function whose strings
    both every writer's lines and the listing a person confirms are made of."""
    return [Listed(v.address, fmt_value(v.new, v.unit), fmt_value(v.old, v.unit), v.unit,
                   v.name) for v in vals]


@dataclass(frozen=True)
class CompensationOutput:
    """What a writer gives: the text to apply or enter, its file name, the values it writes."""

    text: str
    filename: str
    values: list[Value]

    @property
    def listing(self) -> list[Listed]:
        """Every address the text writes, with the value as written (``listing``)."""
        return listing(self.values)


Orientation = Callable[[ControllerParamSpec, float], list[tuple[str, float, str]]]
"""A family's orientation writes: (spec, link in rad) → [(address, control value, unit)] (a
Siemens tilt of an inclined axis moves several axis-vector components)."""


def fixed(v: float, decimals: int = 6) -> str:
    """``v`` with fixed decimals: never an exponent, never ``-0.000000``; refuses a value that
    is not finite or beyond ``MAX_VALUE``."""
    if not isinstance(v, int | float) or not math.isfinite(v) or abs(v) >= MAX_VALUE:
        raise CompensationError(f"value {v!r} is not a finite number below {MAX_VALUE:.0f}")
    s = f"{float(v):.{decimals}f}"
    return s[1:] if s.startswith("-") and float(s) == 0 else s


def fmt_value(v: float, unit: str) -> str:
    """A control value as written: mm and deg with 6 decimals, a unit-less vector component
    (Siemens axis vector) with 9 (1 nrad)."""
    return fixed(v, 9 if unit == "1" else 6)


def degrees(spec: ControllerParamSpec, rad: float) -> list[tuple[str, float, str]]:
    """An orientation as the held link's angle in degrees (Fanuc, Heidenhain)."""
    return [(spec.address, math.degrees(rad), "deg")]


def check_header(run_id: str, machine: str) -> None:
    """Refuse a run id or machine name that could break out of a comment or a file name."""
    if not isinstance(run_id, str) or not RUN_ID.fullmatch(run_id):
        raise CompensationError(f"invalid run id {run_id!r}: expected 1-64 letters, digits "
                                "or '-', starting with a letter or digit")
    if not isinstance(machine, str) or not SAFE_NAME.fullmatch(machine):
        raise CompensationError(f"invalid machine name {machine!r}: expected 1-32 letters, "
                                "digits, '_', '.', '-'")


def comment(text: str) -> str:
    """Text for a program comment, refused unless it is plain (``programs.dialects``' rule)."""
    try:
        return safe_text(text)
    except ProgramError as e:
        raise CompensationError(str(e)) from None


def filename(run_id: str, machine: str, ext: str, rollback: bool) -> str:
    check_header(run_id, machine)
    return f"{'rollback' if rollback else 'compensation'}-{machine}-{run_id}.{ext}"


def values(spec: ControllerKinematics, changes: Sequence[ParamChange], *,
           orientation: Orientation | None = None, rollback: bool = False) -> list[Value]:
    """Old and new control values of every address the changes touch, in the order of the
    section; ``orientation`` converts a link (rad) to the control's unit (None: refused)."""
    by_name = {p.name: p for p in spec.params}
    seen: set[str] = set()
    table: dict[str, list] = {}  # address → [names, old, new, unit]

    def add(name: str, address: str, old: float, new: float, unit: str) -> None:
        row = table.setdefault(address, [[], old, old, unit])
        row[0].append(name)
        row[2] += new - old

    for p in spec.params:  # a section built by hand, not by the loader: no injection either
        for address in (p.address, p.closing or "x", *p.also):
            if not _ADDRESS.fullmatch(address) or not SAFE_NAME.fullmatch(p.name):
                raise CompensationError(f"{p.name!r}: address {address!r} or name not plain")
    for c in changes:
        p = by_name.get(c.name)
        if p is None:
            raise CompensationError(f"change of {c.name!r}: not a parameter of the "
                                    f"{spec.family} section ({', '.join(by_name)})")
        if c.name in seen:
            raise CompensationError(f"{c.name}: changed twice")
        seen.add(c.name)
        if c.kind != p.kind:
            raise CompensationError(f"{c.name}: change of kind {c.kind!r}, parameter is {p.kind}")
        if not isinstance(c.delta, int | float) or not math.isfinite(c.delta):
            raise CompensationError(f"{c.name}: change {c.delta!r} is not a finite number")
        if p.kind == "pivot":
            add(p.name, p.address, p.value, p.value + c.delta, "mm")
            if p.closing is not None:
                old = p.closing_value or 0.0
                add(p.name, p.closing, old, old - c.delta, "mm")
        else:
            if orientation is None:
                raise CompensationError(f"{c.name}: a {spec.family} control has no "
                                        "orientation parameter")
            olds = orientation(p, p.value * 1e-6)
            news = orientation(p, p.value * 1e-6 + c.delta)
            for (address, old, unit), (_, new, _) in zip(olds, news, strict=True):
                add(p.name, address, old, new, unit)
    out = []
    for address, (names, old, new, unit) in table.items():
        # as written (finite and in range, or refused here): the journal holds what the
        # control holds
        old, new = float(fmt_value(old, unit)), float(fmt_value(new, unit))
        pair = (new, old) if rollback else (old, new)
        out.append(Value("+".join(names), address, pair[0], pair[1], unit))
    return out


def describe(r: Listed) -> str:
    """``x-offset: old 12.500000 new 12.606000 mm`` (the comment of every writer)."""
    return f"{r.name}: old {r.was} new {r.written} {r.unit}"


def title(run_id: str, machine: str, rollback: bool) -> str:
    check_header(run_id, machine)
    what = "ROLLBACK" if rollback else "COMPENSATION"
    return f"RUMBA {what} RUN {run_id} MACHINE {machine}"


__all__ = ["MAX_VALUE", "RUN_ID", "UNIT_TEXT", "CompensationError", "CompensationOutput",
           "Listed", "Orientation", "Value", "check_header", "comment", "degrees", "describe",
           "filename", "fixed", "fmt_value", "listing", "title", "values"]


def operator_page(vals: Sequence[Value], *, run_id: str, machine: str, rollback: bool,
                  instructions: Sequence[str], address_label: str, with_unit: bool
                  ) -> CompensationOutput:
    """A page of values the operator enters by hand (controls whose write rumba does not own):
    title, instructions, then one row per value with its address, old and new."""
    unit_head = "  unit" if with_unit else ""
    lines = [comment(title(run_id, machine, rollback)), *instructions, "",
             f"{address_label:>8}  {'name':<24} {'old':>16} {'new':>16}{unit_head}"]
    for r in listing(vals):
        unit = f"  {r.unit}" if with_unit else ""
        lines.append(f"{r.address:>8}  {r.name:<24} {r.was:>16} {r.written:>16}{unit}")
    return CompensationOutput("\n".join(lines) + "\n", filename(run_id, machine, "txt", rollback),
                              list(vals))
