"""pylsv2 on the event loop: its blocking calls on one worker thread (pylsv2 is not thread-safe:
one telegram at a time), every failure one ``LinkError`` naming the call and the TNC's error;
files through a private temporary folder (pylsv2 transfers from and to local paths)."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import shutil
import struct
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import pyLSV2
from pyLSV2.err import (
    LSV2DataException,
    LSV2InputException,
    LSV2ProtocolException,
    LSV2StateException,
)

from drivers.base import LinkError
from drivers.lsv2.schema import Lsv2LinkConfig
from drivers.retry import Refused

T = TypeVar("T")
for _name in ("LSV2 Client", "LSV2 TCP", "pyLSV2"):
    logging.getLogger(_name).setLevel(logging.CRITICAL)  # rumba says what failed, once


class Lsv2Session:
    """One LSV2 connection: INSPECT and FILE (pylsv2's connect), DNC for the program state.

    pylsv2's safe mode (its "lockout": only INSPECT, FILE and MONITOR logins) blocks DNC, which
    the program state needs; rumba opens it and itself never asks for any login but INSPECT,
    FILE and DNC (no PLCDEBUG, no key codes, no machine parameters)."""

    def __init__(self, cfg: Lsv2LinkConfig) -> None:
        self.cfg = cfg
        self.con: Any = None
        self.control = ""
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="lsv2")
        self._tmp = Path(tempfile.mkdtemp(prefix="rumba-lsv2-"))

    @property
    def where(self) -> str:
        return f"lsv2 {self.cfg.host}:{self.cfg.port}"

    async def call(self, what: str, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` on the worker thread; pylsv2's and the socket's failures → LinkError."""
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._pool, fn, *args)
        except ConnectionRefusedError as e:
            raise Refused(f"{self.where}: {e}") from None
        except (OSError, LSV2ProtocolException, struct.error) as e:
            self.con = None  # the connection is unusable after a half telegram
            raise LinkError(f"{self.where}: {what}: {type(e).__name__} {e}".rstrip()) from None
        except (LSV2StateException, LSV2DataException, LSV2InputException, ValueError,
                NotImplementedError) as e:  # refused or not understood: the line still works
            raise LinkError(f"{self.where}: {what}: {e or type(e).__name__}") from None
        except Exception as e:  # pylsv2 raises a bare Exception for a malformed error
            self.con = None  # telegram (found by tests/test_lsv2_link.py's fuzz): a protocol
            raise LinkError(f"{self.where}: {what}: protocol error from the TNC: "  # error
                            f"{type(e).__name__} {str(e)[:80]}") from None

    def _open(self) -> tuple[Any, str, bool]:
        con = pyLSV2.LSV2(self.cfg.host, port=self.cfg.port, timeout=self.cfg.timeout_s,
                          safe_mode=False)
        try:
            con.connect()
            return con, con.versions.control, bool(con.parameters.dnc_mode_allowed)
        except BaseException:
            with contextlib.suppress(Exception):
                con.disconnect()
            raise

    async def open(self) -> None:
        con, control, dnc = await self.call("connect", self._open)
        if not dnc:
            await self.call("disconnect", con.disconnect)
            raise LinkError(f"{self.where}: the {control} does not allow DNC access (its "
                            "machine parameter for the DNC / remote access; see "
                            "drivers/README.md): program state not readable")
        if not await self.call("login DNC", con.login, pyLSV2.Login.DNC):
            await self.call("disconnect", con.disconnect)
            raise LinkError(f"{self.where}: the {control} refused the DNC login")
        self.con, self.control = con, control

    async def close(self) -> None:
        con, self.con = self.con, None
        if con is not None:
            with contextlib.suppress(LinkError):
                await self.call("disconnect", con.disconnect)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
        shutil.rmtree(self._tmp, ignore_errors=True)

    def _con(self) -> Any:
        if self.con is None:
            raise LinkError(f"{self.where}: not connected")
        return self.con

    # ------------------------------------------------------------------ program state
    async def program_state(self) -> int:
        state = await self.call("program state", self._con().program_status)
        return int(state)

    async def selected_program(self) -> str:
        stack = await self.call("selected program", self._con().program_stack)
        return "" if stack is None else str(stack.main)

    # ------------------------------------------------------------------ files
    async def ensure_directory(self, path: str) -> None:
        if not await self.call(f"make directory {path}", self._con().make_directory, path):
            raise LinkError(f"{self.where}: cannot create {path} on the TNC")

    async def exists(self, path: str) -> int | None:
        """The file's size, None when it does not exist."""
        info = await self.call(f"file info {path}", self._con().file_info, path)
        return None if info is None else int(info.size)

    async def delete(self, path: str) -> None:
        if not await self.call(f"delete {path}", self._con().delete_file, path):
            raise LinkError(f"{self.where}: {path} not deleted (in use on the TNC?)")

    async def put(self, path: str, text: str) -> None:
        """Write ``text`` (ASCII) to ``path`` on the TNC, replacing it."""
        try:
            data = text.encode("ascii")
        except UnicodeEncodeError as e:
            raise LinkError(f"{path}: character {text[e.start]!r} is not ASCII: not sent"
                            ) from None
        local = self._tmp / path.rpartition("\\")[2]
        local.write_bytes(data)
        ok = await self.call(f"send {path}", self._con().send_file, local, path, True)
        if not ok:
            raise LinkError(f"{self.where}: {path} not written (the TNC refused it: file in "
                            f"use, protected or no space)")

    async def get(self, path: str) -> str:
        """The text of ``path`` on the TNC (pylsv2 turns the TNC's NUL line ends into CR LF)."""
        local = self._tmp / ("get-" + path.rpartition("\\")[2])
        ok = await self.call(f"read {path}", self._con().recive_file, path, local, True)
        if not ok:
            raise LinkError(f"{self.where}: {path} not read")
        return local.read_bytes().decode("latin1")

