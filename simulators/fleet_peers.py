"""Real PostgreSQL and mosquitto servers for the fleet tests, demo and benchmark: each in its
own temporary directory, on a free loopback port, started and stopped by the caller.

PostgreSQL refuses to run as root: when we are root the cluster belongs to the ``postgres``
account Debian's package creates and its commands run through ``runuser -u postgres``.
Authentication is ``trust`` on loopback only (a test cluster, never a production recipe).
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path


class PeerUnavailable(RuntimeError):
    """The server binary is not installed (bash .ci/install-peers.sh postgresql mosquitto)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_port(port: int, timeout_s: float, proc: subprocess.Popen | None = None) -> None:
    """Until something accepts on 127.0.0.1:port (a readiness check, not a delay)."""
    deadline = time.monotonic() + timeout_s
    while True:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.5):
            return
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"server on port {port} exited with {proc.returncode}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"nothing listens on 127.0.0.1:{port} after {timeout_s} s")
        time.sleep(0.05)


def pg_bin() -> Path:
    dirs = sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda p: int(p.split("/")[-2]))
    if not dirs or not Path(dirs[-1], "pg_ctl").exists():
        raise PeerUnavailable("PostgreSQL not installed (bash .ci/install-peers.sh postgresql)")
    return Path(dirs[-1])


class PostgresPeer:
    """``initdb`` + ``pg_ctl start`` in a temp dir; ``stop()``/``start()`` again on the same
    port (the outage tests); ``close()`` removes everything."""

    def __init__(self, *, fsync: bool = True, max_connections: int = 100) -> None:
        self.bin = pg_bin()
        self.dir = Path(tempfile.mkdtemp(prefix="rumba-pg-"))
        self.port = free_port()
        self.as_user: list[str] = []
        if os.getuid() == 0:
            pw = pwd.getpwnam("postgres")
            os.chown(self.dir, pw.pw_uid, pw.pw_gid)
            self.as_user = ["runuser", "-u", "postgres", "--"]
        self.data = self.dir / "data"
        self._run("initdb", "-D", str(self.data), "-U", "rumba", "--auth=trust", "-E", "UTF8",
                  "--no-sync", "--no-instructions")
        self.opts = (f"-k {self.dir} -p {self.port} -h 127.0.0.1"
                     f" -c fsync={'on' if fsync else 'off'} -c max_connections={max_connections}"
                     " -c shared_buffers=64MB")
        self.start()
        self._run("createdb", "-h", "127.0.0.1", "-p", str(self.port), "-U", "rumba", "rumba")

    @property
    def dsn(self) -> str:
        return f"postgresql://rumba@127.0.0.1:{self.port}/rumba"

    def _run(self, tool: str, *args: str) -> None:
        r = subprocess.run([*self.as_user, str(self.bin / tool), *args], capture_output=True,
                           text=True, timeout=60, cwd=self.dir)
        if r.returncode != 0:
            raise RuntimeError(f"{tool} failed ({r.returncode}): {r.stderr.strip()[-500:]}")

    def start(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.dir / "log"), "-o", self.opts,
                  "-w", "-t", "60", "start")

    def stop(self, mode: str = "fast") -> None:
        """``fast``: clients are disconnected at once (the outage of the tests)."""
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", "60", "stop")

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.stop("immediate")
        shutil.rmtree(self.dir, ignore_errors=True)


class MosquittoPeer:
    """mosquitto on a free loopback port; ``users`` {name: password} turns anonymous access
    off (password file made by ``mosquitto_passwd``); ``tls`` (cert, key) adds TLS."""

    def __init__(self, *, users: dict[str, str] | None = None,
                 tls: tuple[Path, Path] | None = None, port: int | None = None) -> None:
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        if not Path(exe).exists():
            raise PeerUnavailable("mosquitto not installed (bash .ci/install-peers.sh mosquitto)")
        self.exe = exe
        self.dir = Path(tempfile.mkdtemp(prefix="rumba-mqtt-"))
        self.port = port or free_port()
        lines = [f"listener {self.port} 127.0.0.1", "persistence false",
                 f"log_dest file {self.dir / 'log'}", "log_type error", "log_type warning",
                 f"allow_anonymous {'false' if users else 'true'}"]
        if os.getuid() == 0:
            lines.append("user root")  # else it drops to 'mosquitto', who cannot read our dir
        if users:
            pw = self.dir / "passwd"
            pw.touch(mode=0o600)
            for name, password in users.items():
                subprocess.run(["mosquitto_passwd", "-b", str(pw), name, password], check=True,
                               capture_output=True, timeout=30)
            lines.append(f"password_file {pw}")
        if tls:
            lines += [f"certfile {tls[0]}", f"keyfile {tls[1]}"]
        (self.dir / "mosquitto.conf").write_text("\n".join(lines) + "\n")
        self.proc: subprocess.Popen | None = None
        self.start()

    def start(self) -> None:
        self.proc = subprocess.Popen([self.exe, "-c", str(self.dir / "mosquitto.conf")],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        wait_port(self.port, 20.0, self.proc)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.proc = None

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.dir, ignore_errors=True)
