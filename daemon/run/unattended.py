"""Unattended compensation: after a run the CNC started at start of shift, where the machine's
guards allow it (``controller_kinematics.guards.unattended: true``) and rumba writes the values
live (LinuxCNC on this PC), the proposal is applied within the guards, journaled as confirmed by
``unattended``, and a verification run follows at once. Any refusal leaves the machine as it was
and is journaled; an operator-started run never compensates by itself."""

# The write (halcmd setp/getp, the HAL file replaced with fsyncs) takes seconds and runs in a
# worker thread with a journal connection of its own, never on the event loop: the daemon
# keeps serving the HMI, OPC UA and every other machine meanwhile. It is bounded as a whole
# (``halkins.budget``: past ``WRITE_BUDGET_S`` it fails and the old values are put back) and
# cancellation-safe: a cancel (the daemon stopping) waits for the transaction to end — pins,
# HAL file and journal agree either way — before it goes on; the run's machine lock is held
# throughout (``lease``), so no run or other writer gets in.

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from daemon.compensation import journal as cj
from daemon.compensation.apply import ApplyError, confirm
from daemon.compensation.propose import (
    CompensationRefused,
    ControllerModelError,
    is_local_linuxcnc,
    propose,
    spec_of,
)
from daemon.machines.setup import MachineSetup
from daemon.run.phases import Refused
from daemon.store.journal import Store
from daemon.store.machine_lock import Lease
from drivers.linuxcnc import halkins

if TYPE_CHECKING:
    from daemon.run.session import Session

log = logging.getLogger("rumba.compensate")

UNATTENDED_TRIGGERS = ("cnc",)  # the controller's start-of-shift request
WRITE_BUDGET_S = 20.0
"""The unattended write as a whole (the pins checked against the journal, setp, the HAL file,
the read-back); putting the old values back after a failure has a budget of its own
(``apply.HAL_RESTORE_BUDGET_S``). Within the unit's stop timeout with the report's wait."""


def _compensate(journal: Path, reports_dir: Path, setup: MachineSetup, run_id: str,
                lease: Lease | None) -> bool:
    """In a worker thread, on a journal connection of its own: propose, journal a refusal,
    or apply as ``unattended``; True when the values were written."""
    store = Store(journal)
    try:
        spec = spec_of(setup)
        assert spec is not None  # checked by the caller
        try:
            p = propose(setup, store, run_id)
        except (CompensationRefused, ControllerModelError) as e:
            cj.record(store, setup.name, run_id, spec.family, "refused", [],
                      confirmed_by="unattended", reason=str(e))
            log.warning("%s %s: unattended compensation refused: %s", setup.name, run_id, e)
            return False
        if p.refusals:
            cj.record(store, setup.name, run_id, spec.family, "refused", p.values,
                      confirmed_by="unattended", reason="; ".join(p.refusals))
            log.warning("%s %s: unattended compensation refused: %s", setup.name, run_id,
                        "; ".join(p.refusals))
            return False
        if not p.values:
            return False  # nothing worth writing: the machine stays as it is
        try:
            # the run's machine lock is this write's (no other writer gets in between)
            with halkins.budget(WRITE_BUDGET_S):
                w = confirm(setup, store, reports_dir, p, "unattended", lease=lease)
        except (CompensationRefused, ApplyError) as e:
            log.error("%s %s: unattended compensation failed: %s", setup.name, run_id, e)
            return False
        log.info("%s %s: compensated unattended (journal #%d): %s", setup.name, run_id,
                 w.row_id, w.note)
        return True
    finally:
        store.close()


async def after_run(session: Session, run_id: str) -> str | None:
    """Compensate after ``run_id`` when every condition holds; the verification run's id."""
    setup = session.setup
    spec = spec_of(setup)
    if (spec is None or not spec.unattended or session.trigger not in UNATTENDED_TRIGGERS
            or not is_local_linuxcnc(setup, spec)):
        return None
    last = cj.last_applied(session.store, setup.name)
    if last is not None and last.verify_run_id in (None, run_id):
        return None  # this run verifies a compensation: never a chain of writes
    work = asyncio.ensure_future(asyncio.to_thread(
        _compensate, session.store.path, session.reports_dir, setup, run_id, session.lease))
    try:
        written = await asyncio.shield(work)
    except asyncio.CancelledError:
        # the transaction is not cut: it ends (bounded by its budget) before the cancel goes on
        await asyncio.wait({work})
        raise
    if not written:
        return None
    try:
        return session.start("rerun")
    except Refused as e:  # the daemon stopping meanwhile: the next run verifies it
        log.warning("%s %s: verification run not started: %s", setup.name, run_id, e)
        return None
