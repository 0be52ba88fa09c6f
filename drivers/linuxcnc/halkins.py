"""The kinematics pins of a LinuxCNC running on this PC: ``halcmd setp``/``getp`` live, the
running configuration's HAL file found and replaced atomically (with a timestamped backup).

``halcmd`` reaches the running HAL through ``RTAPI_FIFO_PATH`` of this process's environment
(unset: LinuxCNC's default), so the daemon must run as a user that may talk to that HAL.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import tempfile
import time
from pathlib import Path

HALCMD = "/usr/bin/halcmd"
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


def halcmd(*args: str, timeout_s: float = 20.0) -> str:
    """Run ``halcmd`` with this process's environment; its stdout, stripped."""
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
    for line in ini.read_text(errors="replace").splitlines():
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
        try:
            text = f.read_text(errors="replace")
        except OSError:
            continue
        if any(re.search(rf"^\s*setp\s+{re.escape(p)}\s", text, re.M) for p in pins):
            return f
    raise HalError(f"no HAL file of {ini} sets {', '.join(pins)} (setp lines expected)")


def replace_file(path: Path, text: str, stamp: str | None = None) -> Path:
    """Keep ``path`` as ``path.rumba-<stamp>.bak`` next to it, then replace it atomically
    with ``text`` (same mode). Returns the backup's path."""
    stamp = stamp or time.strftime("%Y%m%dT%H%M%S")
    backup = path.with_name(f"{path.name}.rumba-{stamp}.bak")
    n = 1
    while backup.exists():  # two writes within a second keep both backups
        backup = path.with_name(f"{path.name}.rumba-{stamp}-{n}.bak")
        n += 1
    try:
        old = path.read_bytes()
        mode = path.stat().st_mode & 0o7777
        backup.write_bytes(old)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
            os.chmod(tmp, mode)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as e:
        raise HalError(f"cannot replace {path}: {e.strerror or e}") from None
    return backup
