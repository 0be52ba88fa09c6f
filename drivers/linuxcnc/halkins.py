"""The kinematics pins of a LinuxCNC running on this PC: ``halcmd setp``/``getp`` live, the
running configuration's HAL file found and replaced atomically (with a timestamped backup).

``halcmd`` reaches the running HAL through ``RTAPI_FIFO_PATH`` of this process's environment
(unset: LinuxCNC's default), so the daemon must run as a user that may talk to that HAL.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import hashlib
import os
import re
import secrets
import shlex
import stat
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

from contracts.input_files import read_bounded

HALCMD = "/usr/bin/halcmd"
MAX_HAL_BYTES = 1 << 20
"""A HAL file or INI rumba reads (and a HAL file it rewrites) is refused beyond 1 MiB: a
machine's are a few kB (the largest LinuxCNC sample configurations ~40 kB); a larger one is a
wrong path (a log, a device) whose reading would only fill the memory."""
READBACK_REL = 1e-6
"""A read-back equals the value set when within this × max(1, |value|): ``halcmd getp``
prints 7 significant digits (10 nm at 12.6 mm)."""


def agrees(got: float, want: float) -> bool:
    return abs(got - want) <= READBACK_REL * max(1.0, abs(want))


_PIN = re.compile(r"^[A-Za-z0-9_.-]{1,100}$")


class HalError(RuntimeError):
    """halcmd failed or the HAL file cannot be found or replaced; one line for the operator."""


def _pin(name: str) -> str:
    if not _PIN.fullmatch(name):
        raise HalError(f"invalid HAL pin name {name!r}")
    return name


_DEADLINE: contextvars.ContextVar[tuple[float, float] | None] = contextvars.ContextVar(
    "halkins_deadline", default=None)


@contextlib.contextmanager
def budget(seconds: float, *, fresh: bool = False) -> Iterator[None]:
    """Every ``halcmd`` within the block ends by ``seconds`` from now (its own timeout cut to
    what is left, none started once it is spent): a write to the controller is bounded as a
    whole, not only call by call. Within an outer budget the earlier end holds, unless
    ``fresh`` (putting the old values back must not be cut by the spent budget of the write
    that failed). Per thread / task (a context variable)."""
    end = time.monotonic() + seconds
    outer = _DEADLINE.get()
    if outer is not None and not fresh and outer[0] < end:
        end, seconds = outer
    token = _DEADLINE.set((end, seconds))
    try:
        yield
    finally:
        _DEADLINE.reset(token)


def halcmd(*args: str, timeout_s: float = 20.0) -> str:
    """Run ``halcmd`` with this process's environment; its stdout, stripped. Within a
    ``budget`` the timeout is what is left of it."""
    limit = _DEADLINE.get()
    if limit is not None:
        left = limit[0] - time.monotonic()
        if left <= 0:
            raise HalError(f"halcmd {' '.join(args)}: not started, the write's {limit[1]:g} s "
                           "budget is spent")
        timeout_s = min(timeout_s, left)
    try:
        out = subprocess.run([HALCMD, *args], capture_output=True, text=True,
                             timeout=timeout_s, check=False, env=dict(os.environ))
    except (OSError, subprocess.TimeoutExpired) as e:
        raise HalError(f"halcmd {' '.join(args)}: {e}") from None
    if out.returncode != 0:
        msg = " ".join((out.stderr or out.stdout).split())[:200]
        raise HalError(f"halcmd {' '.join(args)} failed (exit {out.returncode}): {msg}")
    return out.stdout.strip()


def getp(pin: str) -> float:
    text = halcmd("getp", _pin(pin))
    try:
        return float(text)
    except ValueError:
        raise HalError(f"halcmd getp {pin}: not a number: {text!r}") from None


def setp(pin: str, value: float) -> None:
    halcmd("setp", _pin(pin), repr(float(value)))


def read_pins(pins: list[str]) -> dict[str, float]:
    return {p: getp(p) for p in pins}


def running_ini() -> Path | None:
    """The INI file of the LinuxCNC running on this PC (its task process's ``-ini``)."""
    for p in os.listdir("/proc"):
        if not p.isdigit():
            continue
        try:
            if Path(f"/proc/{p}/comm").read_text().strip() != "milltask":
                continue
            argv = Path(f"/proc/{p}/cmdline").read_bytes().decode().split("\0")
        except OSError:
            continue
        if "-ini" in argv and argv.index("-ini") + 1 < len(argv):
            ini = Path(argv[argv.index("-ini") + 1])
            if not ini.is_absolute():
                try:
                    ini = Path(os.readlink(f"/proc/{p}/cwd")) / ini
                except OSError:
                    continue
            return ini
    return None


def hal_files(ini: Path) -> list[Path]:
    """The ``[HAL] HALFILE`` entries of ``ini`` that are plain files (not ``LIB:`` or .tcl)."""
    out, section = [], ""
    text = read_bounded(ini, HalError, MAX_HAL_BYTES, "LinuxCNC INI file")
    for line in text.decode("utf-8", "replace").splitlines():
        s = line.strip()
        m = re.match(r"\[(\w+)\]", s)
        if m:
            section = m.group(1)
            continue
        if section == "HAL" and "=" in s and not s.startswith("#"):
            key, value = (x.strip() for x in s.split("=", 1))
            if key == "HALFILE" and not value.startswith("LIB:"):
                words = shlex.split(value)
                if words and words[0].endswith(".hal"):
                    p = Path(words[0])
                    out.append(p if p.is_absolute() else ini.parent / p)
    return out


def hal_file_with(ini: Path, pins: list[str]) -> Path:
    """The HAL file of ``ini`` that sets the kinematics pins (``setp PIN value``)."""
    for f in hal_files(ini):
        if not f.is_file():  # absent (or a FIFO, a device …): not the file with the pins
            continue
        # a file too large or unreadable is refused, never skipped: it may hold the pins
        text = read_bounded(f, HalError, MAX_HAL_BYTES, "HAL file").decode("utf-8", "replace")
        if any(re.search(rf"^\s*setp\s+{re.escape(p)}\s", text, re.M) for p in pins):
            return f
    raise HalError(f"no HAL file of {ini} sets {', '.join(pins)} (setp lines expected)")


class HalFileChanged(HalError):
    """The HAL file is not what rumba read: someone edited it meanwhile; nothing was written."""


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def read_file(path: Path) -> bytes:
    """The HAL file's bytes; a symbolic link is refused, not followed: rumba (often root) never
    writes through a link it did not choose, and replacing the link by a regular file would
    leave its target — what LinuxCNC may really load — stale."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as e:
        if e.errno == errno.ELOOP:
            target = os.readlink(path) if path.is_symlink() else "?"
            raise HalError(f"{path} is a symbolic link (to {target}): rumba does not write "
                           "through links; point the INI's HALFILE at the real file") from None
        raise HalError(f"cannot read {path}: {e.strerror or e}") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise HalError(f"{path} is not a regular file")
        with os.fdopen(os.dup(fd), "rb") as f:
            data = f.read(MAX_HAL_BYTES + 1)
    finally:
        os.close(fd)
    if len(data) > MAX_HAL_BYTES:
        raise HalError(f"{path}: larger than {MAX_HAL_BYTES} bytes: not a HAL file rumba "
                       "rewrites (check the INI's HALFILE)")
    return data


def _create(path: Path, data: bytes, mode: int) -> None:
    """A new file with ``data``, fsynced; O_EXCL|O_NOFOLLOW: an existing name (a planted
    symlink, dangling or not, included) is FileExistsError, never written through."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                 0o600)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fchmod(fd, mode)
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        path.unlink(missing_ok=True)
        raise
    os.close(fd)


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def replace_file(path: Path, text: str, stamp: str | None = None, *,
                 expect: bytes | None = None, backup: bool = True) -> Path | None:
    """Replace ``path`` with ``text`` as one step: a temporary file beside it (same directory,
    O_EXCL|O_NOFOLLOW, same mode and owner), fsync, compare-and-swap (the file must still hold
    ``expect``, what the caller read and patched, else ``HalFileChanged`` and nothing
    changes), rename, fsync of the directory. ``backup``: keep the old bytes as
    ``path.rumba-<stamp>[-n].bak`` first (created exclusively: a name already taken, by a
    file or a planted symlink, is skipped). Returns the backup's path."""
    stamp = stamp or time.strftime("%Y%m%dT%H%M%S")
    try:
        old = read_file(path)
        if expect is not None and sha256(old) != sha256(expect):
            raise HalFileChanged(f"{path} changed since rumba read it (edited meanwhile?): "
                                 "nothing written; run again to patch the new content")
        st = os.lstat(path)
        mode = st.st_mode & 0o7777
        saved = None
        if backup:
            for n in range(100):
                name = f"{path.name}.rumba-{stamp}{f'-{n}' if n else ''}.bak"
                try:
                    _create(path.with_name(name), old, mode)
                except FileExistsError:
                    continue  # two writes within a second keep both; a planted link is skipped
                saved = path.with_name(name)
                break
            else:
                raise HalError(f"no free backup name for {path} (100 taken)")
        tmp = path.with_name(f".{path.name}.rumba-{secrets.token_hex(6)}.tmp")
        _create(tmp, text.encode("utf-8"), mode)
        try:
            with contextlib.suppress(PermissionError):  # keep the owner when we are root
                os.chown(tmp, st.st_uid, st.st_gid, follow_symlinks=False)
            # the swap: still the bytes we read (the window left is this read to the rename)
            if sha256(read_file(path)) != sha256(old):
                raise HalFileChanged(f"{path} changed while rumba wrote it (edited "
                                     "meanwhile?): nothing written; run again")
            os.rename(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        _fsync_dir(path.parent)
    except OSError as e:
        raise HalError(f"cannot replace {path}: {e.strerror or e}") from None
    return saved
