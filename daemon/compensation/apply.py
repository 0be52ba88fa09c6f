"""Compensation write-back, the writing half: the reviewed program/page per controller family
(programs.compensation) in the reports directory, LinuxCNC on this PC live through HAL (setp,
HAL file patched with a backup, getp read-back), journal rows, rollback."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from contracts.controller_kinematics import ControllerKinematics
from daemon.compensation import journal as cj
from daemon.compensation.listing import (
    before_row,
    current_spec,
    expected_values,
    fingerprint,
    listing_lines,
    program_of,
    with_closing,
)
from daemon.compensation.names import UNATTENDED, BadName, validate_by
from daemon.compensation.propose import (
    CompensationRefused,
    ControllerModelError,
    Proposal,
    changed_since,
    check_hal_agrees,
    is_local_linuxcnc,
    spec_of,
)
from daemon.machines.setup import MachineSetup
from daemon.safepath import contained_path
from daemon.store import machine_lock
from daemon.store.compensation_rows import unfinished_run
from daemon.store.journal import Store
from daemon.store.machine_lock import Lease, MachineBusy
from programs.compensation import CompensationOutput

HAL_WRITE_BUDGET_S = 10.0
"""The live write to a LinuxCNC on this PC as a whole (every setp, the HAL file, the
read-back): each halcmd takes well under a second; past this the write fails and the old
values are put back (``halkins.budget``)."""
HAL_RESTORE_BUDGET_S = 10.0
"""Putting the old values back after a failed write: a budget of its own."""


class ApplyError(Exception):
    """Writing to the controller failed; the journal says how far it got."""


@dataclass
class Written:
    row_id: int
    state: str
    path: Path | None  # the program/page in the reports directory
    text: str
    note: str  # what happened on the controller (or what the operator must do)
    program: CompensationOutput | None = None  # what was written, with its listing


def write_program(out: CompensationOutput, reports_dir: Path) -> Path:
    """The family's reviewed program/page (``listing.program_of``), written into
    ``reports_dir`` under the writer's file name (kept inside the directory)."""
    reports_dir.mkdir(parents=True, exist_ok=True)
    path = contained_path(reports_dir, out.filename)
    path.write_text(out.text, encoding="utf-8")
    return path


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
        with halkins.budget(HAL_WRITE_BUDGET_S):
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
        with halkins.budget(HAL_RESTORE_BUDGET_S, fresh=True):
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


def _write(family: str, reports_dir: Path, out: CompensationOutput, by: str, local: bool,
           link: Any = None) -> tuple[Path, str]:
    """Program/page for the record, then the controller itself where rumba can reach it
    (``link``: the machine's link section; a SINUMERIK's file system takes the program)."""
    try:
        path = write_program(out, reports_dir)
    except OSError as e:  # the row is reserved: journal it as a failed write
        raise ApplyError(f"{out.filename} not written: {e}") from None
    if local:
        note = hal_write(out.values)
    elif getattr(link, "transport", "") == "sinumerik":
        note = _send_to_sinumerik(link, out.text, path, by)
    else:
        note = (f"{family}: the operator loads/enters {path.name} on the control "
                f"(confirmed by {by})")
    # what the controller gets, address by address, kept with the journal row
    return path, note + "; writes " + ", ".join(f"{r.address}={r.written}"
                                                 for r in out.listing)


def _send_to_sinumerik(link: Any, text: str, path: Path, by: str) -> str:
    """The reviewed program into the control's "Part Programs" over its OPC UA file system
    (not selected, not started: a person does that at the machine); when the control cannot
    be reached the operator loads the file from the reports directory, as without the link."""
    from drivers.base import LinkError
    from drivers.sinumerik.transfer import COMPENSATION_PROGRAM, send_part_program_blocking

    try:
        name = send_part_program_blocking(link, COMPENSATION_PROGRAM, text)
    except (LinkError, OSError) as e:
        return (f"siemens: {path.name} NOT sent to the control ({e}): the operator loads it "
                f"there (confirmed by {by})")
    return (f"siemens: sent to the control's Part Programs as {name} (a copy of {path.name}): "
            f"the operator selects it and presses NC start (confirmed by {by})")


def _no_run(store: Store, machine: str) -> None:
    """Under the machine lock: a run of this machine the journal shows as not ended refuses
    the write (naming it). A live run holds the lock itself; one left behind by a crash is
    marked INTERRUPTED when the daemon starts again."""
    row = unfinished_run(store, machine)
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
            again: bool = False, lease: Lease | None = None, seen: str | None = None
            ) -> Written:
    """Apply an accepted proposal (operator confirmation ``by``) as one transaction on the
    machine: under its lock (``lease``: one the caller holds, the unattended path's run),
    refused while a run of the machine is not over, re-checked against the journal, the
    program made again from the values the controller holds and refused unless its listing
    is the proposal's (and, given ``seen``, the one the person confirmed: its
    ``listing.fingerprint``), reserved in the journal as decision n of the run (a second
    confirm of one run is refused there; after a rollback only ``again`` makes a new
    decision), then written and journaled with old and new values. An ApplyError is journaled
    as refused (old values restored)."""
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
        out = program_of(current_spec(p.spec, store, setup.name), p.values, p.run_id,
                         setup.name)
        if p.program is None or out.listing != p.program.listing:
            raise CompensationRefused("the program made now differs from the proposal's "
                                      "listing: propose again")
        now_seen = fingerprint(family, p.run_id, out.listing)
        if seen is not None and seen != now_seen:
            raise CompensationRefused(
                f"the values to write are not the ones reviewed (listing {seen}, now "
                f"{now_seen}): reload the proposal and review it again:\n"
                + "\n".join(listing_lines(out.listing)))
        local = _check_hal(setup, p.spec, store)
        decision = max((d.decision or 0 for d in prior), default=0) + 1
        try:
            row = cj.begin_apply(store, setup.name, p.run_id, family, p.values,
                                 confirmed_by=by, decision=decision)
        except cj.DecisionTaken as e:
            raise CompensationRefused(str(e)) from None
        try:
            path, note = _write(family, reports_dir, out, by, local, setup.link)
        except ApplyError as e:
            cj.finish_apply(store, row, "refused", p.values, str(e), None)
            raise ApplyError(f"{e} (journal #{row})") from None
        cj.finish_apply(store, row, "applied", with_closing(p.values, out.values), note,
                        time.time())
    return Written(row, "applied", path, out.text, note, out)


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
        before = before_row(spec, last)
        local = _check_hal(setup, before, store)
        try:
            out = program_of(before, last.values, last.run_id, setup.name, rollback=True)
            path, note = _write(spec.family, reports_dir, out, by, local, setup.link)
        except (ApplyError, CompensationRefused) as e:
            row = cj.record(store, setup.name, last.run_id, spec.family, "refused", values,
                            confirmed_by=by, reason=f"{reason}: {e}")
            raise ApplyError(f"{e} (journal #{row})") from None
        with store.transaction():
            cj.update(store, last.id, state="rolled_back")
            row = cj.record(store, setup.name, last.run_id, spec.family, "rolled_back",
                            values, confirmed_by=by, reason=f"{reason}; {note}",
                            applied_at=time.time())
    return Written(row, "rolled_back", path, out.text, note, out)
