"""What a compensation writes, address by address: the controller's values now, the program a
confirmation would write from them, and its listing (the strings the person confirms)."""

# The review surfaces (HMI dialog, `rumba compensate`, the review document, the report) show
# ``CompensationOutput.listing`` of the same ``render`` call that makes the program: every
# address the program writes, with the value as the program writes it, in the controller's
# unit and sign ($TC_CARR10[1] = -0.000026670 for a +26.67 µrad EB0C on a −z C axis, the
# closing $TC_CARR18[1] a pivot change moves too). ``fingerprint`` names one listing: a
# confirmation carries the one the person saw and is refused when the program differs.

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from typing import Any

from contracts.controller_kinematics import ControllerKinematics
from daemon.compensation import journal as cj
from daemon.compensation.identified import CompensationRefused
from daemon.store.journal import Store
from identification.compensation import ParamChange
from programs.compensation import CompensationError, CompensationOutput, Listed, render
from programs.compensation.common import UNIT_TEXT

CLOSING = " closing"
"""Journal name suffix of a value the writer changes besides the parameter's own address
(Siemens: the offset vector that keeps the chain closed)."""


def expected_values(spec: ControllerKinematics, store: Store, machine: str
                    ) -> dict[str, tuple[str, float]]:
    """name → (address, value the controller should hold): the journal's last written value,
    else the machine file's."""
    current = cj.current_values(store, machine)
    return {p.name: (p.address, current[p.name].new if p.name in current else float(p.value))
            for p in spec.params}


def spec_at(spec: ControllerKinematics, values: dict[str, float],
            closing: dict[str, float] | None = None) -> ControllerKinematics:
    """The section with the given values (by parameter name) and closing values (by address)
    in place of the file's."""
    closing = closing or {}
    return dataclasses.replace(spec, params=tuple(
        dataclasses.replace(p, value=values.get(p.name, p.value),
                            closing_value=closing.get(p.closing or "", p.closing_value))
        for p in spec.params))


def current_spec(spec: ControllerKinematics, store: Store, machine: str) -> ControllerKinematics:
    """The section with every value as the controller holds it now (journal, else file)."""
    now = expected_values(spec, store, machine)
    closing = {}
    for row in cj.written(store, machine):
        for v in row.values:
            if v.name.endswith(CLOSING):
                closing[v.address] = v.new
    return spec_at(spec, {name: v for name, (_, v) in now.items()}, closing)


def before_row(spec: ControllerKinematics, row: cj.CompensationRow) -> ControllerKinematics:
    """The section as the controller held it before ``row`` was written."""
    return spec_at(spec, {v.name: v.old for v in row.values},
                   {v.address: v.old for v in row.values if v.name.endswith(CLOSING)})


def math_changes(spec: ControllerKinematics, values: Sequence[cj.ValueChange]
                 ) -> list[ParamChange]:
    """The parameters' changes (closing entries are the writer's consequence, not changes)."""
    return [ParamChange(v.name, spec.param(v.name).kind, v.delta, v.u_expanded, True)
            for v in values if not v.name.endswith(CLOSING)]


def with_closing(values: Sequence[cj.ValueChange], written: Sequence) -> list[cj.ValueChange]:
    """``values`` plus what the writer changes at other addresses (journaled too)."""
    own = {v.address for v in values}
    return [*values, *(cj.ValueChange(w.name + CLOSING, w.address, w.unit, w.old, w.new,
                                      w.new - w.old) for w in written if w.address not in own)]


def program_of(spec_base: ControllerKinematics, values: Sequence[cj.ValueChange], run_id: str,
               machine: str, rollback: bool = False) -> CompensationOutput:
    """The family's program/page for these changes from the values of ``spec_base``
    (``rollback``: from new back to them), not written anywhere; refused with one line when the
    writer cannot write it."""
    try:
        return render(spec_base, math_changes(spec_base, values), run_id=run_id,
                      machine=machine, rollback=rollback)
    except CompensationError as e:
        raise CompensationRefused(f"{spec_base.family} program not written: {e}") from None


def fingerprint(family: str, run_id: str, listing: Sequence[Listed]) -> str:
    """16 hex digits naming one listing of one run: what a confirmation says it saw."""
    text = "\n".join([family, run_id, *(r.text() for r in listing)])
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def listing_json(listing: Sequence[Listed]) -> list[dict[str, Any]]:
    """The listing for the page, the review document and the report."""
    return [{"address": r.address, "written": r.written, "was": r.was, "unit": r.unit,
             "name": r.name, "text": r.text()} for r in listing]


def listing_lines(listing: Sequence[Listed], indent: str = "  ") -> list[str]:
    """One line per address as the program writes it, aligned for a terminal."""
    width = max((len(r.address) for r in listing), default=0)
    return [f"{indent}{r.address:<{width}} = {r.written:>14}  (was {r.was}; "
            f"{UNIT_TEXT.get(r.unit, r.unit)}; {r.name})" for r in listing]


def row_listing(spec: ControllerKinematics, row: cj.CompensationRow) -> list[Listed]:
    """What a journaled write put on the controller, address by address (the same writer, from
    the values the controller held before it); [] when the section no longer names them."""
    try:  # a rollback row holds the reversed changes: written forward from its old values
        return program_of(before_row(spec, row), row.values, row.run_id or "R",
                          row.machine).listing
    except (CompensationRefused, KeyError, ValueError):
        return []


__all__ = ["CLOSING", "before_row", "current_spec", "expected_values", "fingerprint",
           "listing_json", "listing_lines", "math_changes", "program_of", "row_listing",
           "spec_at", "with_closing"]
