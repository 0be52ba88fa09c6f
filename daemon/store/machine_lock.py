"""One machine, one writer: the lock a verification run, a compensation confirm or rollback
(CLI, HMI, unattended) takes on a machine, across threads and processes.

An ``flock`` on a file beside the journal, one per machine (``.<journal>.machine-<name>.lock``).
``flock`` belongs to the open file, not to the process: two acquisitions in one daemon (a run
and an HMI confirm) exclude each other like a CLI process and the daemon do, and the kernel
drops the lock when its holder dies (kill -9 leaves no stale lease to clean up). The holder
writes who it is into the file, so a refusal names it ("run 20260101-… (CAPTURE)").
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import re
from pathlib import Path

_NAME = re.compile(r"\A[A-Za-z0-9_.-]{1,64}\Z")


class MachineBusy(Exception):
    """Another run or compensation holds the machine; the message names it (one line)."""

    def __init__(self, machine: str, holder: str) -> None:
        super().__init__(f"machine {machine} is busy: {holder or 'another rumba process'} "
                         "holds it; try again once it has ended")
        self.machine, self.holder = machine, holder


def lock_path(journal: Path | str, machine: str) -> Path:
    """The lock file of ``machine`` beside the journal ``journal``."""
    j = Path(journal)
    if not _NAME.fullmatch(machine) or machine.startswith("."):
        # machine names are checked safe names; anything else still gets its own file
        machine = hashlib.sha256(machine.encode()).hexdigest()[:16]
    return j.with_name(f".{j.name}.machine-{machine}.lock")


class Lease:
    """A held machine lock; ``release()`` is idempotent (a done-callback and a handover may
    both call it)."""

    def __init__(self, machine: str, fd: int, holder: str) -> None:
        self.machine, self.holder, self._fd = machine, holder, fd

    @property
    def held(self) -> bool:
        return self._fd >= 0

    def describe(self, holder: str) -> None:
        """Say who holds it now (a run knows its id only once it has the lock)."""
        self.holder = holder
        if self._fd >= 0:
            text = f"{holder} (pid {os.getpid()})".encode()
            os.ftruncate(self._fd, 0)
            os.pwrite(self._fd, text, 0)

    def release(self) -> None:
        fd, self._fd = self._fd, -1
        if fd >= 0:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)  # nobody holds it: a later refusal must not name us
            os.close(fd)  # closing the last descriptor drops the flock

    def __enter__(self) -> Lease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _open(path: Path) -> int:
    # O_NOFOLLOW: rumba may run as root; a planted symlink at the lock's name is not followed
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    except OSError as e:
        raise MachineBusy(path.stem, f"(lock file {path} unusable: {e.strerror or e})") from None


def acquire(journal: Path | str, machine: str, holder: str) -> Lease:
    """Take ``machine``'s lock now (never waits) for ``holder`` (e.g. ``"run X (PREPARE)"``),
    else ``MachineBusy`` naming whoever holds it."""
    path = lock_path(journal, machine)
    fd = _open(path)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        try:
            who = os.pread(fd, 512, 0).decode("utf-8", "replace").strip()
        finally:
            os.close(fd)
        raise MachineBusy(machine, who) from None
    except OSError:
        os.close(fd)
        raise
    text = f"{holder} (pid {os.getpid()})".encode()
    os.ftruncate(fd, 0)
    os.pwrite(fd, text, 0)
    return Lease(machine, fd, holder)


def holder_of(journal: Path | str, machine: str) -> str | None:
    """Who holds ``machine`` now, or None when it is free (for status and messages)."""
    try:
        lease = acquire(journal, machine, "probe")
    except MachineBusy as e:
        return e.holder or "another rumba process"
    lease.release()
    return None
