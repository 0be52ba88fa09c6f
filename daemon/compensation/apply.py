"""Compensation write-back, the writing half: the reviewed program/page per controller family
(programs.compensation) in the reports directory, LinuxCNC on this PC live through HAL (setp,
HAL file patched with a backup, getp read-back), journal rows, rollback."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

from contracts.controller_kinematics import ControllerKinematics
from daemon.compensation import journal as cj
from daemon.compensation.propose import (
    CompensationRefused,
    ControllerModelError,
    Proposal,
    check_hal_agrees,
    expected_values,
    is_local_linuxcnc,
    spec_of,
)
from daemon.machines.setup import MachineSetup
from daemon.safepath import contained_path
from daemon.store.journal import Store
from identification.compensation import ParamChange


class ApplyError(Exception):
    """Writing to the controller failed; the journal says how far it got."""


@dataclass
class Written:
    row_id: int
    state: str
    path: Path | None  # the program/page in the reports directory
    text: str
    note: str  # what happened on the controller (or what the operator must do)


CLOSING = " closing"
"""Journal name suffix of a value the writer changes besides the parameter's own address
(Siemens: the offset vector that keeps the chain closed)."""


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


def math_changes(spec: ControllerKinematics, values: list[cj.ValueChange]) -> list[ParamChange]:
    """The parameters' changes (closing entries are the writer's consequence, not changes)."""
    return [ParamChange(v.name, spec.param(v.name).kind, v.delta, v.u_expanded, True)
            for v in values if not v.name.endswith(CLOSING)]


def with_closing(values: list[cj.ValueChange], written: list) -> list[cj.ValueChange]:
    """``values`` plus what the writer changes at other addresses (journaled too)."""
    own = {v.address for v in values}
    return [*values, *(cj.ValueChange(w.name + CLOSING, w.address, w.unit, w.old, w.new,
                                      w.new - w.old) for w in written if w.address not in own)]


def write_program(spec_base: ControllerKinematics, values: list[cj.ValueChange],
                  reports_dir: Path, run_id: str, machine: str, rollback: bool = False
                  ) -> tuple[Path, str, list]:
    """The family's reviewed program/page (programs.compensation.<family>) for these changes
    from the values of ``spec_base`` (``rollback``: from new back to them), written into
    ``reports_dir`` under the writer's file name (kept inside the directory); with the
    writer's values (programs.compensation.common.Value)."""
    from programs.compensation import CompensationError, render

    try:
        out = render(spec_base, math_changes(spec_base, values), run_id=run_id,
                     machine=machine, rollback=rollback)
    except CompensationError as e:
        raise CompensationRefused(f"{spec_base.family} program not written: {e}") from None
    reports_dir.mkdir(parents=True, exist_ok=True)
    path = contained_path(reports_dir, out.filename)
    path.write_text(out.text, encoding="utf-8")
    return path, out.text, list(out.values)


def hal_write(values: list, hal_file: Path | None = None) -> str:
    """LinuxCNC on this PC: setp live, patch the running configuration's HAL file (backup
    beside it, atomic replace), getp read-back. ``values``: the writer's (address, old, new).
    On a failure before the read-back the old values are set again."""
    from drivers.linuxcnc import halkins
    from programs.compensation import CompensationError, patch_hal_file

    new = {v.address: v.new for v in values}
    old = {v.address: v.old for v in values}
    try:
        if hal_file is None:
            ini = halkins.running_ini()
            if ini is None:
                raise halkins.HalError("no running LinuxCNC found on this PC (no milltask)")
            hal_file = halkins.hal_file_with(ini, list(new))
        patched = patch_hal_file(hal_file.read_text(encoding="utf-8"), values)
        for pin, v in new.items():
            halkins.setp(pin, v)
        backup = halkins.replace_file(hal_file, patched)
        back = halkins.read_pins(list(new))
    except (halkins.HalError, CompensationError, OSError) as e:
        _restore(old)
        raise ApplyError(f"LinuxCNC write failed, old values set again: {e}") from None
    bad = [f"{p} {back[p]!r} != {v!r}" for p, v in new.items()
           if not halkins.agrees(back[p], v)]
    if bad:
        raise ApplyError(f"LinuxCNC read-back differs: {'; '.join(bad)} (HAL file {hal_file} "
                         f"already patched, backup {backup})")
    return f"set live with halcmd and read back; HAL file {hal_file} patched (backup {backup})"


def _restore(old: dict[str, float]) -> None:
    from drivers.linuxcnc import halkins

    for pin, v in old.items():
        with contextlib.suppress(halkins.HalError):
            halkins.setp(pin, v)


def _write(setup: MachineSetup, store: Store, reports_dir: Path, spec_base: ControllerKinematics,
           values: list[cj.ValueChange], run_id: str, by: str, rollback: bool
           ) -> tuple[Path, str, str, list]:
    """Program/page for the record, then the controller itself where rumba can reach it (a
    LinuxCNC whose live pins differ from the journal is refused before anything is set)."""
    local = is_local_linuxcnc(setup, spec_base)
    if local:
        try:
            check_hal_agrees(setup, spec_base, store)
        except ControllerModelError as e:
            raise CompensationRefused(str(e)) from None
    path, text, written = write_program(spec_base, values, reports_dir, run_id, setup.name,
                                        rollback)
    if local:
        note = hal_write(written)
    else:
        note = (f"{spec_base.family}: the operator loads/enters {path.name} on the control "
                f"(confirmed by {by})")
    return path, text, note, written


def confirm(setup: MachineSetup, store: Store, reports_dir: Path, p: Proposal, by: str
            ) -> Written:
    """Apply an accepted proposal (operator confirmation ``by``), journaled with old and new
    values; an ApplyError is journaled as refused (old values restored) and raised."""
    if p.refusals:
        raise CompensationRefused("; ".join(p.refusals))
    if not p.values:
        raise CompensationRefused("nothing to apply: every change is skipped ("
                                  + "; ".join(f"{k}: {v}" for k, v in p.skipped.items()) + ")")
    if by == "unattended" and not p.spec.unattended:
        raise CompensationRefused(f"machine {setup.name}: unattended compensation is not "
                                  "allowed (controller_kinematics.guards.unattended: false)")
    family = p.spec.family
    try:
        spec_now = current_spec(p.spec, store, setup.name)
        path, text, note, written = _write(setup, store, reports_dir, spec_now, p.values,
                                           p.run_id, by, False)
    except ApplyError as e:
        row = cj.record(store, setup.name, p.run_id, family, "refused", p.values,
                        confirmed_by=by, reason=str(e))
        raise ApplyError(f"{e} (journal #{row})") from None
    row = cj.record(store, setup.name, p.run_id, family, "applied",
                    with_closing(p.values, written), confirmed_by=by, reason=note,
                    applied_at=time.time())
    return Written(row, "applied", path, text, note)


def rollback(setup: MachineSetup, store: Store, reports_dir: Path, by: str) -> Written:
    """Restore the values before the last applied compensation: that row becomes
    'rolled_back' and a new 'rolled_back' row records the restore."""
    spec = spec_of(setup)
    if spec is None:
        raise CompensationRefused(f"machine {setup.name}: no controller_kinematics section")
    last = cj.last_applied(store, setup.name)
    if last is None:
        raise CompensationRefused(f"machine {setup.name}: no applied compensation to roll back")
    values = [v.reversed() for v in last.values]
    reason = f"{cj.ROLLBACK_PREFIX}{last.id}"
    before = spec_at(spec, {v.name: v.old for v in last.values},
                     {v.address: v.old for v in last.values if v.name.endswith(CLOSING)})
    try:
        path, text, note, _ = _write(setup, store, reports_dir, before, list(last.values),
                                     last.run_id, by, True)
    except ApplyError as e:
        row = cj.record(store, setup.name, last.run_id, spec.family, "refused", values,
                        confirmed_by=by, reason=f"{reason}: {e}")
        raise ApplyError(f"{e} (journal #{row})") from None
    with store.transaction():
        cj.update(store, last.id, state="rolled_back")
        row = cj.record(store, setup.name, last.run_id, spec.family, "rolled_back", values,
                        confirmed_by=by, reason=f"{reason}; {note}", applied_at=time.time())
    return Written(row, "rolled_back", path, text, note)
