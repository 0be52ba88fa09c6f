"""The command channel to LinuxCNC: linuxcncrsh's line protocol over TCP, or the same command
subset answered by the local helper (drivers/linuxcnc/local.py) over a child process's pipes."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import sys
from pathlib import Path

from drivers.base import LinkError
from drivers.linuxcnc.schema import LinuxCncLinkConfig

HELPER = Path(__file__).resolve().parent / "local.py"


class RshChannel:
    """linuxcncrsh line protocol over TCP (replies end in \\r\\n or \\n\\r; echo turned off)."""

    name = "linuxcncrsh"

    def __init__(self, cfg: LinuxCncLinkConfig) -> None:
        self.cfg = cfg
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self._buf = b""

    async def open(self) -> None:
        c = self.cfg
        try:
            self.reader, self.writer = await asyncio.wait_for(
                asyncio.open_connection(c.host, c.port), c.connect_timeout_s)
        except (OSError, TimeoutError) as e:
            raise LinkError(f"linuxcncrsh at {c.host}:{c.port} unreachable: "
                            f"{e.strerror if isinstance(e, OSError) else 'timeout'}") from None
        rep = await self.ask(f"hello {c.hello_password} {c.client_name} 1.0")
        if not rep.startswith("HELLO ACK"):
            raise LinkError(f"linuxcncrsh refused hello: {rep!r} (check hello_password)")
        self.send("set echo off")  # echoed itself (or not): synchronise on the next reply
        self.send("get echo")
        while await self.line(self.cfg.connect_timeout_s) != "ECHO OFF":
            pass
        # set_wait received: a `set mdi` answers once LinuxCNC has taken the block (after the
        # previous one finished). `done` would poll completion in 100 ms steps (linuxcncrsh).
        for cmd in ("set verbose on", f"set enable {c.enable_password}",
                    "set set_wait received"):
            rep = await self.ask(cmd)
            if not rep.endswith("ACK"):
                raise LinkError(f"linuxcncrsh: {cmd.split()[1]} refused: {rep!r}")

    def send(self, cmd: str) -> None:
        if self.writer is None:
            raise LinkError("linuxcncrsh: not connected")
        self.writer.write(cmd.encode("ascii") + b"\r\n")

    async def line(self, timeout_s: float) -> str:
        assert self.reader is not None
        while True:
            m = re.search(rb"[^\r\n]+[\r\n]", self._buf)
            if m:
                self._buf = self._buf[m.end():]
                return m.group()[:-1].decode("ascii", "replace")
            try:
                data = await asyncio.wait_for(self.reader.read(4096), timeout_s)
            except TimeoutError:
                raise LinkError(f"{self.name} silent for {timeout_s:g} s") from None
            except OSError as e:
                raise LinkError(f"{self.name} connection lost: {e}") from None
            if not data:
                raise LinkError(f"{self.name} closed the connection (LinuxCNC stopped?)")
            self._buf += data

    async def ask(self, cmd: str, timeout_s: float | None = None) -> str:
        self.send(cmd)
        return await self.line(timeout_s or self.cfg.command_timeout_s)

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            with contextlib.suppress(Exception):
                await self.writer.wait_closed()
        self.reader = self.writer = None
        self._buf = b""


class LocalChannel(RshChannel):
    """The same command subset answered by drivers/linuxcnc/local.py through the ``linuxcnc``
    module, in a child process of Debian's /usr/bin/python3 (the only one that has it)."""

    name = "local LinuxCNC helper"

    def __init__(self, cfg: LinuxCncLinkConfig) -> None:
        super().__init__(cfg)
        self.proc: asyncio.subprocess.Process | None = None

    async def open(self) -> None:
        try:
            env = dict(os.environ)
            if self.cfg.local_home:  # linuxcnc.stat() maps $HOME/.tool.mmap of the instance
                env["HOME"] = self.cfg.local_home
            self.proc = await asyncio.create_subprocess_exec(
                self.cfg.helper_python, "-I", str(HELPER), stdin=asyncio.subprocess.PIPE,
                stdout=asyncio.subprocess.PIPE, stderr=sys.stderr, env=env)
        except OSError as e:
            raise LinkError(f"cannot start {self.cfg.helper_python} {HELPER}: {e}") from None
        self.reader, self.writer = self.proc.stdout, self.proc.stdin  # type: ignore[assignment]
        rep = await self.line(self.cfg.connect_timeout_s)
        if not rep.startswith("HELLO ACK"):
            raise LinkError(f"local LinuxCNC helper: {rep}")

    async def line(self, timeout_s: float) -> str:
        rep = await super().line(timeout_s)
        if rep.startswith("LOST "):  # the helper saw LinuxCNC's task process die, and ended
            raise LinkError(rep.removeprefix("LOST "))
        return rep

    async def close(self) -> None:
        if self.proc is not None and self.proc.returncode is None:
            with contextlib.suppress(Exception):
                self.proc.stdin.close()  # type: ignore[union-attr]
            try:
                await asyncio.wait_for(self.proc.wait(), 3)
            except TimeoutError:
                self.proc.kill()
                await self.proc.wait()
        self.proc = None
        self.reader = self.writer = None
