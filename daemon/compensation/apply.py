"""Compensation write-back, the writing half: the reviewed program/page per controller family
(programs.compensation) in the reports directory, LinuxCNC on this PC live through HAL (setp,
HAL file patched with a backup, getp read-back), journal rows, rollback."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from contracts.controller_kinematics import ControllerKinematics
from daemon.compensation import journal as cj
from daemon.compensation.names import UNATTENDED, BadName, validate_by
from daemon.compensation.propose import (
    CompensationRefused,
    ControllerModelError,
    Proposal,
    changed_since,
    check_hal_agrees,
    expected_values,
    is_local_linuxcnc,
    spec_of,
)
from daemon.machines.setup import MachineSetup
from daemon.safepath import contained_path
from daemon.store import machine_lock
from daemon.store.journal import FINAL_STATES, Store
from daemon.store.machine_lock import Lease, MachineBusy
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
    """LinuxCNC on this PC: the live pins and the running configuration's HAL file changed
    together or not at all. The file is read first (a symlink refused before anything is
    set) and patched; then setp live, the file replaced (temp file beside it, fsync, rename,
    compare-and-swap on what was read, backup created exclusively), getp read-back. Any
    failure sets the old values again and puts the file's old content back (only over the
    content rumba wrote: an edit made meanwhile is kept and named). ``values``: the writer's
    (address, old, new)."""
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
        original = halkins.read_file(hal_file)
        patched = patch_hal_file(original.decode("utf-8"), values)
    except (halkins.HalError, CompensationError, OSError, UnicodeDecodeError) as e:
        raise ApplyError(f"LinuxCNC write refused, nothing set: {e}") from None
    replaced = False
    try:
        for pin, v in new.items():
            halkins.setp(pin, v)
        backup = halkins.replace_file(hal_file, patched, expect=original)
        replaced = True
        back = halkins.read_pins(list(new))
        bad = [f"{p} {back[p]!r} != {v!r}" for p, v in new.items()
               if not halkins.agrees(back[p], v)]
        if bad:
            raise halkins.HalError(f"read-back differs: {'; '.join(bad)}")
    except (halkins.HalError, OSError) as e:
        _restore(old)
        where = _restore_file(hal_file, original, patched) if replaced else \
            f"HAL file {hal_file} unchanged"
        raise ApplyError(f"LinuxCNC write failed, old values set again, {where}: {e}") from None
    return f"set live with halcmd and read back; HAL file {hal_file} patched (backup {backup})"


def _restore_file(path: Path, original: bytes, written: str) -> str:
    """Put ``original`` back into ``path`` over the content rumba wrote (compare-and-swap);
    what happened, for the message and the journal."""
    from drivers.linuxcnc import halkins

    try:
        halkins.replace_file(path, original.decode("utf-8"), expect=written.encode("utf-8"),
                             backup=False)
    except halkins.HalError as e:
        return f"HAL file {path} NOT restored ({e}): restore it by hand"
    return f"HAL file {path} restored"


def _restore(old: dict[str, float]) -> None:
    from drivers.linuxcnc import halkins

    for pin, v in old.items():
        with contextlib.suppress(halkins.HalError):
            halkins.setp(pin, v)


def _check_hal(setup: MachineSetup, spec: ControllerKinematics, store: Store) -> bool:
    """A LinuxCNC on this PC whose live pins differ from the journal is refused before
    anything is set; True when rumba writes this controller live."""
    if not is_local_linuxcnc(setup, spec):
        return False
    try:
        check_hal_agrees(setup, spec, store)
    except ControllerModelError as e:
        raise CompensationRefused(str(e)) from None
    return True


def _write(setup: MachineSetup, reports_dir: Path, spec_base: ControllerKinematics,
           values: list[cj.ValueChange], run_id: str, by: str, rollback: bool, local: bool
           ) -> tuple[Path, str, str, list]:
    """Program/page for the record, then the controller itself where rumba can reach it."""
    try:
        path, text, written = write_program(spec_base, values, reports_dir, run_id,
                                            setup.name, rollback)
    except CompensationRefused as e:  # the row is reserved: journal it as a failed write
        raise ApplyError(str(e)) from None
    if local:
        note = hal_write(written)
    elif getattr(setup.link, "transport", "") == "sinumerik":
        note = _send_to_sinumerik(setup, text, path, by)
    else:
        note = (f"{spec_base.family}: the operator loads/enters {path.name} on the control "
                f"(confirmed by {by})")
    return path, text, note, written


def _send_to_sinumerik(setup: MachineSetup, text: str, path: Path, by: str) -> str:
    """The reviewed program into the control's "Part Programs" over its OPC UA file system
    (not selected, not started: a person does that at the machine); when the control cannot
    be reached the operator loads the file from the reports directory, as without the link."""
    from drivers.base import LinkError
    from drivers.sinumerik.transfer import COMPENSATION_PROGRAM, send_part_program_blocking

    try:
        name = send_part_program_blocking(setup.link, COMPENSATION_PROGRAM, text)
    except (LinkError, OSError) as e:
        return (f"siemens: {path.name} NOT sent to the control ({e}): the operator loads it "
                f"there (confirmed by {by})")
    return (f"siemens: sent to the control's Part Programs as {name} (a copy of {path.name}): "
            f"the operator selects it and presses NC start (confirmed by {by})")


def _no_run(store: Store, machine: str) -> None:
    """Under the machine lock: a run of this machine the journal shows as not ended refuses
    the write (naming it). A live run holds the lock itself; one left behind by a crash is
    marked INTERRUPTED when the daemon starts again."""
    placeholders = ",".join("?" * len(FINAL_STATES))
    row = store.db.execute(
        f"SELECT id, state FROM runs WHERE machine=? AND state NOT IN ({placeholders}) "
        "ORDER BY started_at DESC LIMIT 1", (machine, *FINAL_STATES)).fetchone()
    if row is not None:
        raise CompensationRefused(f"machine {machine}: run {row[0]} is in {row[1]} in the "
                                  "journal: compensate once it has ended")


@contextlib.contextmanager
def _locked(store: Store, machine: str, what: str, lease: Lease | None) -> Iterator[Lease]:
    """The machine's lock for this write (``lease``: one the caller already holds, used as
    it is); a busy machine is a refusal naming its holder."""
    if lease is not None and lease.held:
        yield lease
        return
    try:
        own = machine_lock.acquire(store.path, machine, what)
    except MachineBusy as e:
        raise CompensationRefused(str(e)) from None
    with own:
        _no_run(store, machine)
        yield own


def _name(by: str) -> str:
    try:
        return validate_by(by)
    except BadName as e:
        raise CompensationRefused(str(e)) from None


def confirm(setup: MachineSetup, store: Store, reports_dir: Path, p: Proposal, by: str, *,
            again: bool = False, lease: Lease | None = None) -> Written:
    """Apply an accepted proposal (operator confirmation ``by``) as one transaction on the
    machine: under its lock (``lease``: one the caller holds, the unattended path's run),
    refused while a run of the machine is not over, re-checked against the journal, reserved
    in the journal as decision n of the run (a second confirm of one run is refused there;
    after a rollback only ``again`` makes a new decision), then written and journaled with
    old and new values. An ApplyError is journaled as refused (old values restored)."""
    by = _name(by)
    if p.refusals:
        raise CompensationRefused("; ".join(p.refusals))
    if not p.values:
        raise CompensationRefused("nothing to apply: every change is skipped ("
                                  + "; ".join(f"{k}: {v}" for k, v in p.skipped.items()) + ")")
    if by == UNATTENDED and not p.spec.unattended:
        raise CompensationRefused(f"machine {setup.name}: unattended compensation is not "
                                  "allowed (controller_kinematics.guards.unattended: false)")
    family = p.spec.family
    with _locked(store, setup.name, f"compensation of run {p.run_id} by {by}", lease):
        # re-checked under the lock: the proposal was computed before it was taken
        prior = cj.decisions(store, p.run_id)
        last = prior[-1] if prior else None
        if last is not None and last.state in ("applied", "applying"):
            raise CompensationRefused(f"run {p.run_id} is already {last.state} (journal "
                                      f"#{last.id}, by {last.confirmed_by}): a run is "
                                      "compensated once")
        if last is not None and not again:
            raise CompensationRefused(
                f"run {p.run_id} was applied and {last.state} (journal #{last.id}, by "
                f"{last.confirmed_by}): confirming it again is a new decision — give --again "
                "(the HMI asks a second time)")
        later = changed_since(store, setup.name, store.run(p.run_id).started_at)
        if later is not None:
            raise CompensationRefused(
                f"the controller's model changed after run {p.run_id} started (journal "
                f"#{later.id}, {later.state}): verify again and compensate from that run")
        now = {n: v for n, (_, v) in expected_values(p.spec, store, setup.name).items()}
        moved = [n for n, v in p.current.items() if abs(now.get(n, v) - v) > 1e-12]
        if moved:  # another writer got in between the proposal and this confirm
            raise CompensationRefused(f"the controller's values changed since this proposal "
                                      f"({', '.join(moved)}): propose again")
        local = _check_hal(setup, p.spec, store)
        decision = max((d.decision or 0 for d in prior), default=0) + 1
        try:
            row = cj.begin_apply(store, setup.name, p.run_id, family, p.values,
                                 confirmed_by=by, decision=decision)
        except cj.DecisionTaken as e:
            raise CompensationRefused(str(e)) from None
        try:
            spec_now = current_spec(p.spec, store, setup.name)
            path, text, note, written = _write(setup, reports_dir, spec_now, p.values,
                                               p.run_id, by, False, local)
        except ApplyError as e:
            cj.finish_apply(store, row, "refused", p.values, str(e), None)
            raise ApplyError(f"{e} (journal #{row})") from None
        cj.finish_apply(store, row, "applied", with_closing(p.values, written), note,
                        time.time())
    return Written(row, "applied", path, text, note)


def rollback(setup: MachineSetup, store: Store, reports_dir: Path, by: str, *,
             lease: Lease | None = None) -> Written:
    """Restore the values before the last applied compensation: that row becomes
    'rolled_back' and a new 'rolled_back' row records the restore; under the machine's lock,
    refused while a run of the machine is not over."""
    by = _name(by)
    spec = spec_of(setup)
    if spec is None:
        raise CompensationRefused(f"machine {setup.name}: no controller_kinematics section")
    with _locked(store, setup.name, f"rollback by {by}", lease):
        last = cj.last_applied(store, setup.name)
        if last is None:
            raise CompensationRefused(f"machine {setup.name}: no applied compensation to roll "
                                      "back")
        values = [v.reversed() for v in last.values]
        reason = f"{cj.ROLLBACK_PREFIX}{last.id}"
        before = spec_at(spec, {v.name: v.old for v in last.values},
                         {v.address: v.old for v in last.values if v.name.endswith(CLOSING)})
        local = _check_hal(setup, before, store)
        try:
            path, text, note, _ = _write(setup, reports_dir, before, list(last.values),
                                         last.run_id, by, True, local)
        except ApplyError as e:
            row = cj.record(store, setup.name, last.run_id, spec.family, "refused", values,
                            confirmed_by=by, reason=f"{reason}: {e}")
            raise ApplyError(f"{e} (journal #{row})") from None
        with store.transaction():
            cj.update(store, last.id, state="rolled_back")
            row = cj.record(store, setup.name, last.run_id, spec.family, "rolled_back",
                            values, confirmed_by=by, reason=f"{reason}; {note}",
                            applied_at=time.time())
    return Written(row, "rolled_back", path, text, note)
