"""The Haas NGC data port (Machine Data Collection, Setting 143) as a client: one request at a
time, one answer line each. ``?Q600 <n>`` reads macro variable n (answer ``MACRO, <value>``),
``?E<n> <value>`` writes it (answer ``!``; ``?`` refused), ``?Q500`` the program state
(``PROGRAM, O09100, IDLE, PARTS, 12`` or ``STATUS, BUSY``), ``?Q100`` the serial number. Answers
may come framed by STX … ETB and followed by a ``>`` prompt; both are stripped.

The control sends every connection's answers to all connections (up to two): rumba must be the
port's only client, and a line nobody asked for fails the request instead of being taken for
its answer."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import re

from drivers.base import LinkError
from drivers.cancel import keep_cancel
from drivers.retry import Refused

log = logging.getLogger("rumba.haas")
_MACRO = re.compile(r"^MACRO,\s*([+-]?(?:\d+\.?\d*|\.\d+))$")
MAX_LINE = 256


def clean(raw: bytes) -> str:
    """An answer line without its framing (STX, ETB, CR, the ``>`` prompt)."""
    text = raw.decode("ascii", errors="replace")
    return text.replace("\x02", "").replace("\x17", "").strip().lstrip(">").strip()


def parse_macro(line: str, n: int) -> float:
    """``MACRO, 12.5`` → 12.5; ``LinkError`` for anything else (a value is never guessed)."""
    m = _MACRO.fullmatch(line)
    if not m:
        raise LinkError(f"haas data port: ?Q600 {n} answered {line[:60]!r}, expected "
                        "'MACRO, <number>'")
    value = float(m.group(1))
    if not math.isfinite(value):
        raise LinkError(f"haas data port: #{n} = {line[:60]!r} is not a finite number")
    return value


def parse_status(line: str) -> tuple[str, str]:
    """``?Q500``'s answer → (state, program): ("BUSY", "") while a program runs, else the
    state word (IDLE, ALARM ON, FEED HOLD …) and the program's name."""
    parts = [p.strip() for p in line.split(",")]
    if parts[0] == "STATUS BUSY" or parts[:2] == ["STATUS", "BUSY"]:
        return "BUSY", ""
    if len(parts) >= 3 and parts[0] == "PROGRAM" and parts[2]:
        return parts[2].upper(), parts[1]
    raise LinkError(f"haas data port: ?Q500 answered {line[:60]!r}, expected 'PROGRAM, "
                    "<name>, <state>, PARTS, <n>' or 'STATUS, BUSY'")


class DataPort:
    def __init__(self, host: str, port: int, timeout_s: float) -> None:
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self._writer: asyncio.StreamWriter | None = None
        self._lines: asyncio.Queue[str | BaseException] = asyncio.Queue()
        self._pump: asyncio.Task | None = None
        self._lock = asyncio.Lock()
        # Answers still owed to requests cancelled after they were sent (a run stopped while it
        # polled): each is read and dropped before the next request, never taken for its answer.
        self._owed = 0
        self._waiting = False

    @property
    def where(self) -> str:
        return f"haas {self.host}:{self.port}"

    @property
    def open(self) -> bool:
        return self._writer is not None

    async def connect(self) -> None:
        try:
            async with asyncio.timeout(self.timeout_s):
                reader, self._writer = await asyncio.open_connection(
                    self.host, self.port, limit=MAX_LINE * 4)
        except ConnectionRefusedError as e:
            raise Refused(f"{self.where}: {e}") from None
        except (TimeoutError, OSError) as e:
            raise LinkError(f"{self.where}: {e or type(e).__name__}") from None
        self._lines = asyncio.Queue()
        self._owed, self._waiting = 0, False
        self._pump = asyncio.create_task(self._read_lines(reader, self._lines))

    async def close(self) -> None:
        writer, self._writer = self._writer, None
        pump, self._pump = self._pump, None
        if pump is not None:
            pump.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await pump
        if writer is not None:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    async def _read_lines(self, reader: asyncio.StreamReader,
                          lines: asyncio.Queue[str | BaseException]) -> None:
        """Every answer line as it arrives (empty lines and prompts dropped); the connection's
        end or a line beyond ``MAX_LINE`` as an error for the waiting request."""
        try:
            while True:
                raw = await reader.readuntil(b"\n")
                if len(raw) > MAX_LINE:
                    raise LinkError(f"{self.where}: answer of {len(raw)} bytes (noise?)")
                line = clean(raw)
                if line:
                    lines.put_nowait(line)
        except asyncio.CancelledError:
            raise
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, OSError) as e:
            lines.put_nowait(LinkError(f"{self.where}: connection lost ({type(e).__name__})"))
        except LinkError as e:
            lines.put_nowait(e)

    async def request(self, command: str) -> str:
        """Send ``command``, return its answer line; ``LinkError`` on a timeout, a dropped
        connection, or a line nobody asked for (another client's answer: Haas sends answers
        to every connection)."""
        async with self._lock:
            if self._writer is None:
                raise LinkError(f"{self.where}: not connected")
            await self._settle_owed(command)
            if not self._lines.empty():
                stray = self._lines.get_nowait()
                if isinstance(stray, BaseException):
                    await self.close()
                    raise stray
                raise LinkError(f"{self.where}: unexpected line {stray[:60]!r} before "
                                f"{command!r}: another client on the data port? (the control "
                                "sends every answer to all connections)")
            try:
                self._writer.write(command.encode("ascii") + b"\r\n")
                self._waiting = True
                async with asyncio.timeout(self.timeout_s):
                    await self._writer.drain()
                    answer = await keep_cancel(self._answer())
            except asyncio.CancelledError:
                if self._waiting:  # sent, its answer not read: the next request drops it
                    self._owed += 1
                    self._waiting = False
                raise
            except (TimeoutError, OSError) as e:
                await self.close()
                raise LinkError(f"{self.where}: {command}: no answer "
                                f"({type(e).__name__})") from None
            if isinstance(answer, BaseException):
                await self.close()
                raise answer
            return answer

    async def _answer(self) -> str | BaseException:
        answer = await self._lines.get()
        self._waiting = False
        return answer

    async def _settle_owed(self, command: str) -> None:
        """Read and drop the answers of cancelled requests (within the request timeout each);
        a connection that never gives them is closed: it is out of step."""
        while self._owed:
            try:
                async with asyncio.timeout(self.timeout_s):
                    line = await self._lines.get()
            except TimeoutError:
                await self.close()
                raise LinkError(f"{self.where}: the answer to a request stopped before "
                                f"{command!r} never came: connection closed") from None
            self._owed -= 1
            if isinstance(line, BaseException):
                await self.close()
                raise line

    async def read(self, n: int) -> float:
        return parse_macro(await self.request(f"?Q600 {n}"), n)

    async def write(self, n: int, value: float) -> None:
        if not math.isfinite(value):
            raise LinkError(f"{self.where}: #{n} = {value!r}: not written")
        answer = await self.request(f"?E{n} {value:.6f}")
        if answer != "!":
            raise LinkError(f"{self.where}: ?E{n} refused ({answer[:40]!r}): a variable the "
                            "data port may not write (Haas allows #1-#33, #500-#699, "
                            "#800-#999 and their NGC numbers)")

    async def status(self) -> tuple[str, str]:
        return parse_status(await self.request("?Q500"))
