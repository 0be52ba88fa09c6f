"""Unattended compensation: after a run the CNC started at start of shift, where the machine's
guards allow it (``controller_kinematics.guards.unattended: true``) and rumba writes the values
live (LinuxCNC on this PC), the proposal is applied within the guards, journaled as confirmed by
``unattended``, and a verification run follows at once. Any refusal leaves the machine as it was
and is journaled; an operator-started run never compensates by itself."""

from __future__ import annotations

import logging
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

if TYPE_CHECKING:
    from daemon.run.session import Session

log = logging.getLogger("rumba.compensate")

UNATTENDED_TRIGGERS = ("cnc",)  # the controller's start-of-shift request


def after_run(session: Session, run_id: str) -> str | None:
    """Compensate after ``run_id`` when every condition holds; the verification run's id."""
    setup, store = session.setup, session.store
    spec = spec_of(setup)
    if (spec is None or not spec.unattended or session.trigger not in UNATTENDED_TRIGGERS
            or not is_local_linuxcnc(setup, spec)):
        return None
    last = cj.last_applied(store, setup.name)
    if last is not None and last.verify_run_id in (None, run_id):
        return None  # this run verifies a compensation: never a chain of writes
    try:
        p = propose(setup, store, run_id)
    except (CompensationRefused, ControllerModelError) as e:
        cj.record(store, setup.name, run_id, spec.family, "refused", [],
                  confirmed_by="unattended", reason=str(e))
        log.warning("%s %s: unattended compensation refused: %s", setup.name, run_id, e)
        return None
    if p.refusals:
        cj.record(store, setup.name, run_id, spec.family, "refused", p.values,
                  confirmed_by="unattended", reason="; ".join(p.refusals))
        log.warning("%s %s: unattended compensation refused: %s", setup.name, run_id,
                    "; ".join(p.refusals))
        return None
    if not p.values:
        return None  # nothing outside its own uncertainty: the machine stays as it is
    try:
        # inside the run's own task: the run's machine lock is this write's (no other writer
        # can get in between the run and its compensation)
        w = confirm(setup, store, session.reports_dir, p, "unattended", lease=session.lease)
    except (CompensationRefused, ApplyError) as e:
        log.error("%s %s: unattended compensation failed: %s", setup.name, run_id, e)
        return None
    log.info("%s %s: compensated unattended (journal #%d): %s", setup.name, run_id, w.row_id,
             w.note)
    return session.start("rerun")
