"""The machine lock of a run: a run holds its machine from PREPARE to its end, so a
compensation (CLI in another process, HMI, unattended) cannot write the controller's kinematics
under it, and a run cannot start while a compensation is being written."""

from __future__ import annotations

from pathlib import Path

from daemon.run.phases import Refused
from daemon.store import machine_lock
from daemon.store.machine_lock import Lease, MachineBusy


def take(previous: Lease | None, journal: Path, machine: str, trigger: str) -> Lease:
    """The machine's lock for a new run started by ``trigger``, else ``Refused`` naming who
    holds it. The session's ``previous`` lease is handed over: a run that ends starts its
    follow-up (the unattended verification) from inside its own task, which still holds the
    lock then; the caller checked that the session is not busy."""
    if previous is not None:
        previous.release()
    try:
        return machine_lock.acquire(journal, machine, f"a run started by {trigger}")
    except MachineBusy as e:
        raise Refused(f"{machine}: {e.holder or 'another rumba process'} holds the machine; "
                      f"{trigger} request refused") from None
