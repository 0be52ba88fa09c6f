"""Build and install config/linuxcnc/xyzbc_head_kins.comp, the swivel head's kinematics."""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
COMP = REPO / "config" / "linuxcnc" / "xyzbc_head_kins.comp"
MODULES = Path("/usr/lib/linuxcnc/modules")
MODULE = MODULES / "xyzbc_head_kins.so"
# uspace rtapi_app loads a module by name from MODULES only (``loadrt`` takes no path: it opens
# "<modules>/<name>.so"), so the module is installed there (``halcompile --install``, as root:
# CI and the tests run as root; elsewhere run this once with sudo). The installed .so carries the
# source's sha256 as a string, so an edited .comp is rebuilt and a current one is not.
TAG = b"rumba-xyzbc-head-kins-src-sha256:"


class HeadKinsError(RuntimeError):
    """The module could not be built or installed; the message says why."""


def source_sha() -> str:
    return hashlib.sha256(COMP.read_bytes()).hexdigest()


def installed() -> bool:
    """The installed module is the one built from today's source."""
    try:
        return TAG + source_sha().encode() in MODULE.read_bytes()
    except OSError:
        return False


def ensure_installed(timeout_s: float = 300.0) -> Path:
    """Build the module with ``halcompile`` and install it unless the current one is there."""
    if installed():
        return MODULE
    if shutil.which("halcompile", path="/usr/bin:/bin") is None:
        raise HeadKinsError("halcompile not found: bash .ci/install-peers.sh linuxcnc (Debian "
                            "linuxcnc-uspace-dev)")
    with tempfile.TemporaryDirectory(prefix="rumba-headkins.") as tmp:
        comp = Path(tmp) / COMP.name
        tag = (TAG + source_sha().encode()).decode()
        comp.write_text(COMP.read_text(encoding="utf-8") + "\n__attribute__((used)) static "
                        f'const char rumba_src_sha256[] = "{tag}";\n', encoding="utf-8")
        try:
            out = subprocess.run(["halcompile", "--install", comp.name], cwd=tmp,
                                 capture_output=True, text=True, timeout=timeout_s, check=False)
        except (OSError, subprocess.TimeoutExpired) as e:
            raise HeadKinsError(f"halcompile --install {COMP}: {e}") from None
        if out.returncode != 0 or not installed():
            tail = " | ".join((out.stdout + out.stderr).strip().splitlines()[-6:])
            raise HeadKinsError(f"halcompile --install {COMP} failed (exit {out.returncode}; "
                                f"installing into {MODULES} needs root): {tail}")
    return MODULE


if __name__ == "__main__":
    print(ensure_installed())
