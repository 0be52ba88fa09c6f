"""Start and stop the LinuxCNC sim machine of config/linuxcnc/ headless, with the HAL probe.

    python -m simulators.linuxcnc_peer up [--errors F] [--artefact F] [--absent B2] [--dir D]
                                          [--ini rumba_swivelhead.ini --machine F]
        → prints LCNC_DIR=… LCNC_PORT=… LCNC_PID=… LCNC_INI=… LCNC_LOG=… (shell lines)
    python -m simulators.linuxcnc_peer down DIR

Only one LinuxCNC runs per machine (fixed NML/HAL shared-memory keys, /tmp/linuxcnc.lock, and a
second start kills the first's processes by name): ``up`` takes an exclusive ``flock`` on
``/tmp/rumba-linuxcnc.flock`` for the life of the process that started it, and refuses when a
LinuxCNC it did not start is running. Root recipe (tests/peers/linuxcnc/NOTES.md):
``RTAPI_UID=65534``, ``RTAPI_FIFO_PATH`` in a 1777 folder directly under /tmp, a scratch
``HOME``, no ``DISPLAY``. ``down`` ends linuxcncrsh (the linuxcnc script then cleans up), kills
what is left of this instance by PID, and — when no LinuxCNC is left — removes the lock file and
the SysV shared memory a hard kill leaves behind (stale segments hang the next start).
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from simulators.linuxcnc_files import write_ini, write_probe_hal

REPO = Path(__file__).resolve().parent.parent
CONFIG = REPO / "config" / "linuxcnc"
INI_NAME = "rumba_xyzbc.ini"
FLOCK = Path("/tmp/rumba-linuxcnc.flock")
SHM_KEYS = (0x3E9, 0x3EA, 0x3EB, 0x3EC, 0x3ED, 0x64, 0x48414C32, 0x48484C34)
_DAEMONS = ("milltask", "linuxcncsvr", "rtapi_app")
_held: dict[str, IO] = {}  # dir → open flock file of an instance this process started


class PeerError(RuntimeError):
    """LinuxCNC could not be started or stopped; the message says why (with the log tail)."""


@dataclass(frozen=True)
class Peer:
    dir: Path
    port: int
    pid: int
    ini: Path
    log: Path

    def env_lines(self) -> str:
        return "\n".join([f"LCNC_DIR={self.dir}", f"LCNC_PORT={self.port}",
                          f"LCNC_PID={self.pid}", f"LCNC_INI={self.ini}", f"LCNC_LOG={self.log}"])


def _alive(pid: int) -> bool:
    try:
        st = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return st != "Z"


def _comm(pid: str) -> str:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return ""


def lcnc_running() -> list[int]:
    """PIDs of live LinuxCNC daemons anywhere on the machine."""
    return [int(p) for p in os.listdir("/proc") if p.isdigit() and _comm(p) in _DAEMONS
            and _alive(int(p))]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _lock(timeout_s: float) -> IO:
    fh = open(FLOCK, "a+")  # noqa: SIM115 - held until down()
    end = time.monotonic() + timeout_s
    while True:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return fh
        except BlockingIOError:
            if time.monotonic() > end:
                fh.close()
                raise PeerError(f"another rumba LinuxCNC holds {FLOCK} (only one LinuxCNC per "
                                f"machine); waited {timeout_s:g} s") from None
            time.sleep(0.2)


def up(spec: Path | None = None, *, port: int | None = None, workdir: Path | None = None,
       timeout_s: float = 60.0, lock_timeout_s: float = 120.0, ini_name: str = INI_NAME) -> Peer:
    """Start LinuxCNC (with the HAL probe reading ``spec`` when given); wait for linuxcncrsh.
    ``ini_name``: the machine of config/linuxcnc/ (``rumba_swivelhead.ini``: the swivel head,
    whose kins module is built and installed first, simulators/linuxcnc_headkins.py)."""
    if shutil.which("linuxcnc", path="/usr/bin:/bin") is None:
        raise PeerError("linuxcnc is not installed (bash .ci/install-peers.sh linuxcnc)")
    if "/" in ini_name or not (CONFIG / ini_name).is_file():
        raise PeerError(f"no machine {ini_name!r} in {CONFIG}")
    if ini_name != INI_NAME:
        from simulators.linuxcnc_headkins import HeadKinsError, ensure_installed

        try:
            ensure_installed()
        except HeadKinsError as e:
            raise PeerError(str(e)) from None
    lock = _lock(lock_timeout_s)
    try:
        others = lcnc_running()
        if others:
            raise PeerError(f"a LinuxCNC not started by us is running (pids {others}); "
                            "only one per machine")
        d = Path(workdir or tempfile.mkdtemp(prefix="rumba-lcnc.")).resolve()
        d.mkdir(parents=True, exist_ok=True)
        if workdir is None:
            (d / ".created-by-linuxcnc-peer").touch()
        port = port or free_port()
        cfg = d / "config"
        shutil.rmtree(cfg, ignore_errors=True)
        shutil.copytree(CONFIG, cfg, ignore=shutil.ignore_patterns("*.md"))
        for sub in ("home", "nc_files"):
            (d / sub).mkdir(exist_ok=True)
        # rtapi_app drops to uid 65534 and binds its fifo there: a 1777 folder directly under
        # /tmp (every parent traversable by that uid; a 0700 mkdtemp parent is not).
        fifo = Path(tempfile.mkdtemp(prefix="rumba-rtapi.", dir="/tmp"))
        fifo.chmod(0o1777)
        (d / "fifo.path").write_text(str(fifo))
        probe_hal = None
        if spec is not None:
            probe_hal = cfg / "rumba_probe.hal"
            write_probe_hal(probe_hal, Path(spec))
        ini = cfg / ini_name
        write_ini(CONFIG / ini_name, ini, port, d / "nc_files", probe_hal)
        env = {k: v for k, v in os.environ.items()
               if k not in ("DISPLAY", "WAYLAND_DISPLAY", "XAUTHORITY", "PYTHONPATH",
                            "VIRTUAL_ENV", "PYTHONHOME")}
        env.update(HOME=str(d / "home"), RTAPI_FIFO_PATH=str(fifo / "rtapi_fifo"),
                   PATH="/usr/bin:/bin:/usr/sbin:/sbin:" + os.environ.get("PATH", ""))
        if os.geteuid() == 0:
            env["RTAPI_UID"] = "65534"
        log = d / "linuxcnc.log"
        with open(log, "wb") as fh:
            # -r keeps stdout/stderr (without a tty linuxcnc writes them to /tmp files it
            # deletes at exit); start_new_session: pgid == pid, so down() finds the group.
            proc = subprocess.Popen(["linuxcnc", "-r", str(ini)], cwd=cfg, env=env,
                                    stdin=subprocess.DEVNULL, stdout=fh, stderr=fh,
                                    start_new_session=True)
        (d / "linuxcnc.pid").write_text(str(proc.pid))
        peer = Peer(d, port, proc.pid, ini, log)
        _held[str(d)] = lock
        end = time.monotonic() + timeout_s
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), 0.5).close()
                return peer
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > end:
                tail = log_tail(log)
                down(d)
                raise PeerError(f"linuxcncrsh did not come up on 127.0.0.1:{port}; log: {tail}")
            time.sleep(0.1)
    except BaseException:
        if lock not in _held.values():
            lock.close()
        raise


def log_tail(log: Path, n: int = 15) -> str:
    try:
        lines = [ln for ln in log.read_text(errors="replace").splitlines()
                 if "fallback_uid" not in ln]
    except OSError:
        return "(no log)"
    return " | ".join(lines[-n:])


def _instance_pids(fifo: str) -> list[int]:
    """Processes of this instance by the RTAPI_FIFO_PATH in their environment (rtapi_app and
    linuxcncsvr leave the process group)."""
    out, me = [], os.getpid()
    for p in os.listdir("/proc"):
        if not p.isdigit() or int(p) == me:
            continue
        try:
            env = Path(f"/proc/{p}/environ").read_bytes()
        except OSError:
            continue
        if f"RTAPI_FIFO_PATH={fifo}/".encode() in env:
            out.append(int(p))
    return out


def _kill(pids: list[int], sig: int) -> None:
    for p in pids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(p, sig)


def down(workdir: Path | str, timeout_s: float = 15.0) -> None:
    """Stop the instance started in ``workdir``; safe when it already exited or was killed."""
    d = Path(workdir)
    try:
        pid = int((d / "linuxcnc.pid").read_text())
        fifo = (d / "fifo.path").read_text().strip()
    except (OSError, ValueError):
        pid, fifo = 0, ""
    if pid and _alive(pid):
        # linuxcnc runs its display (linuxcncrsh) in the foreground and defers its TERM trap
        # until that returns: end linuxcncrsh and the script runs its own Cleanup (~2 s).
        rsh = [int(c) for c in os.listdir("/proc") if c.isdigit() and _comm(c) == "linuxcncrsh"
               and Path(f"/proc/{c}/stat").read_text().rsplit(")", 1)[1].split()[1] == str(pid)]
        _kill(rsh or [pid], signal.SIGTERM)
        end = time.monotonic() + timeout_s
        while _alive(pid) and time.monotonic() < end:
            time.sleep(0.1)
    with contextlib.suppress(ChildProcessError, OSError):
        os.waitpid(pid, os.WNOHANG)
    left = _instance_pids(fifo) if fifo else []
    if pid:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, 0)
            left.append(-pid)
    if left:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for p in left:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(-p, sig) if p < 0 else os.kill(p, sig)
            time.sleep(0.5)
        end = time.monotonic() + 3
        while lcnc_running() and time.monotonic() < end:
            time.sleep(0.1)
    with contextlib.suppress(ChildProcessError, OSError):
        os.waitpid(pid, os.WNOHANG)
    if not lcnc_running():
        with contextlib.suppress(OSError):
            os.unlink("/tmp/linuxcnc.lock")
        _remove_shm()
        # the linuxcnc script's /tmp/linuxcnc.{debug,print}.XXXXXX, deleted by its Cleanup,
        # which a hard kill skips: those made while this instance lived are its own
        with contextlib.suppress(OSError):
            since = (d / "linuxcnc.pid").stat().st_mtime - 1.0
            for f in Path("/tmp").glob("linuxcnc.[dp][er][bi]*.*"):
                if re.fullmatch(r"linuxcnc\.(debug|print)\.\w{6}", f.name) \
                        and f.stat().st_mtime >= since:
                    f.unlink()
    if fifo.startswith("/tmp/rumba-rtapi."):
        shutil.rmtree(fifo, ignore_errors=True)
    if (d / ".created-by-linuxcnc-peer").exists():
        shutil.rmtree(d, ignore_errors=True)
    lock = _held.pop(str(d), None)
    if lock is not None:
        lock.close()


def _remove_shm() -> None:
    """Remove the segments a hard-killed LinuxCNC leaves (only those nobody is attached to)."""
    try:
        out = subprocess.run(["ipcs", "-m"], capture_output=True, text=True, check=False).stdout
    except OSError:
        return
    for line in out.splitlines():
        f = line.split()
        if len(f) >= 6 and f[0].startswith("0x") and int(f[0], 16) in SHM_KEYS and f[5] == "0":
            subprocess.run(["ipcrm", "-m", f[1]], capture_output=True, check=False)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m simulators.linuxcnc_peer", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    u = sub.add_parser("up", help="start LinuxCNC with the HAL probe; print LCNC_* lines")
    u.add_argument("--machine", default=str(REPO / "config/machines/linuxcnc_xyzbc.yaml"))
    u.add_argument("--artefact", default=str(REPO / "config/artefacts/thesis_4ball.yaml"))
    u.add_argument("--errors", default=str(REPO / "config/errors/linuxcnc_xyzbc.yaml"))
    u.add_argument("--absent", action="append", default=[], help="ball id not on the table")
    u.add_argument("--dir", type=Path, help="work folder (default: a new /tmp/rumba-lcnc.*)")
    u.add_argument("--port", type=int)
    u.add_argument("--ini", default=INI_NAME, help="machine of config/linuxcnc/ (e.g. "
                   "rumba_swivelhead.ini with --machine/--errors of linuxcnc_swivelhead)")
    dn = sub.add_parser("down", help="stop the instance of DIR and clean its leftovers")
    dn.add_argument("dir", type=Path)
    a = ap.parse_args(argv)
    if a.cmd == "down":
        down(a.dir)
        return 0
    from contracts.yaml_files import ConfigError
    from simulators.hal_probe import write_spec
    from simulators.truth import TruthModel

    try:
        truth = TruthModel.from_files(a.machine, a.artefact, a.errors)
        d = Path(a.dir or tempfile.mkdtemp(prefix="rumba-lcnc."))
        created = a.dir is None
        spec = d / "probe_spec.json"
        if created:
            (d / ".created-by-linuxcnc-peer").touch()
        write_spec(truth, spec, tuple(a.absent))
        peer = up(spec, port=a.port, workdir=d, ini_name=a.ini)
    except (ConfigError, ValueError, PeerError) as e:
        if a.dir is None and "d" in locals():
            shutil.rmtree(d, ignore_errors=True)  # the folder this call made, nothing started
        print(f"linuxcnc_peer: {e}", file=sys.stderr)
        return 2
    # The flock dies with this process: a shell-driven peer relies on lcnc_running() instead.
    print(peer.env_lines())
    return 0


if __name__ == "__main__":
    sys.exit(main())
