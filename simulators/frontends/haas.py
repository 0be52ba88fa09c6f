"""Controller side of the Haas NGC data port (Machine Data Collection, Setting 143): a TCP server
answering ``?Q100`` (serial number), ``?Q101`` / ``?Q102`` / ``?Q104``, ``?Q500`` (program and
state), ``?Q600 <n>`` (macro variable n: ``MACRO, <value>``) and ``?E<n> <value>`` (``!``, or
``?`` for a variable the port may not write), every answer framed STX … ETB CR LF and sent to
every connection, as the control does (up to two; a third is refused).

Variables are the controller's (legacy numbers #n; the port knows them as #10000 + n on NGC,
``variable_base``). The machine's side: the program O09100 is read from the network share
(``share``) and run when rumba sets program-ready (#693) and ``auto_start`` is on (the shop's
start-of-shift routine or operator, as tests and demos run it), or by ``cycle_start()``; the
start-of-shift request #690 follows the controller's request flag; the structure sensors are
copied into #591-#593 (a macro or the PLC, as the DNC dialect prints them).
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from pathlib import Path
from typing import Any

from simulators import thermal
from simulators.frontends import cancel_tasks
from simulators.frontends.ring_pacing import RingPacer

_Q600 = re.compile(r"^\?Q600\s+(\d{1,6})$")
_E = re.compile(r"^\?E(\d{1,6})\s+([+-]?(?:\d+\.?\d*|\.\d+))$")
WRITABLE = [(1, 33), (500, 699), (800, 999)]  # legacy numbers the port may write
MAX_CLIENTS = 2


def frame(text: str) -> bytes:
    return b"\x02" + text.encode("ascii") + b"\x17\r\n"


class HaasFrontend:
    """One data-port server for one simulated Haas; ``await start()`` returns the port."""

    def __init__(self, controller: Any, share: Path, *, variable_base: int = 10000,
                 auto_start: bool = True, handshake: dict[str, int] | None = None) -> None:
        self.ctrl = controller
        self.share = Path(share)
        self.base = variable_base
        self.auto_start = auto_start
        self.handshake = {"request": 690, "busy": 691, "done": 692, "program_ready": 693,
                          **(handshake or {})}
        self.pacer = RingPacer(controller, "haas")
        self.starts = 0
        self.requests: list[str] = []  # every command received (tests)
        self._writers: set[asyncio.StreamWriter] = set()
        self._server: asyncio.Server | None = None
        self._tasks: list[asyncio.Task] = []
        controller.variable_listeners.append(self._written)

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        self._server = await asyncio.start_server(self._serve, host, port)
        self._tasks = [asyncio.create_task(self._sync()), asyncio.create_task(self._events())]
        return self._server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        await cancel_tasks(self._tasks)
        self.pacer.close()
        if self._written in self.ctrl.variable_listeners:
            self.ctrl.variable_listeners.remove(self._written)
        if self._server is not None:
            self._server.close()
            for w in list(self._writers):
                w.transport.abort()
            await self._server.wait_closed()
            self._server = None

    def diagnose(self) -> str:
        v = self.ctrl.variables
        return (f"ring #599 {v.get('#599')} ack {v.get('#688')} stop {v.get('#689')}, "
                f"handshake { {r: v.get(f'#{n}') for r, n in self.handshake.items()} }, "
                f"starts {self.starts}, held {self.pacer.held}")

    # ------------------------------------------------------------------ the machine's side
    def _var(self, n: int) -> float:
        v = self.ctrl.variables.get(f"#{n}", 0.0)
        return float(v) if isinstance(v, int | float) else 0.0

    def _written(self, name: str, value: Any) -> None:
        role = next((r for r, n in self.handshake.items() if name == f"#{n}"), None)
        if role in ("busy", "done") and isinstance(value, float):
            setattr(self.ctrl, role, value >= 0.5)
        elif role == "program_ready" and self.auto_start and isinstance(value, float) \
                and value >= 0.5 and self.ctrl.state not in ("running", "hold"):
            asyncio.get_running_loop().create_task(self.cycle_start())

    async def cycle_start(self) -> None:
        """The operator (or the start-of-shift routine) runs O09100 from the share."""
        path = self.share / "O09100.nc"
        try:
            text = path.read_text(encoding="ascii")
        except (OSError, UnicodeDecodeError):
            return  # nothing there: the control shows "no program"
        await self.ctrl.load_program(text, "haas")
        await self.ctrl.start()
        self.starts += 1

    async def _events(self) -> None:
        q = self.ctrl.subscribe()
        while True:
            ev = await q.get()
            if type(ev).__name__ == "FaultEvent" and ev.kind == "disconnect":
                for w in list(self._writers):
                    w.transport.abort()

    async def _sync(self) -> None:
        seen = {role: bool(getattr(self.ctrl, role)) for role in ("done", "busy")}
        while True:
            request = f"#{self.handshake['request']}"
            if bool(self.ctrl.request) != (self._var(self.handshake["request"]) >= 0.5):
                self.ctrl.variables[request] = 1.0 if self.ctrl.request else 0.0
            for role in ("done", "busy"):  # cleared on the control's side (its new request)
                now = bool(getattr(self.ctrl, role))
                if now != seen[role] and (self._var(self.handshake[role]) >= 0.5) != now:
                    self.ctrl.variables[f"#{self.handshake[role]}"] = 1.0 if now else 0.0
                seen[role] = now
            for axis, value in self.ctrl.sensor_temperatures().items():
                dict.__setitem__(self.ctrl.variables, thermal.FANUC_VARIABLE[axis], value)
            await asyncio.sleep(0.02)

    def _status(self) -> str:
        state = self.ctrl.state
        if state in ("running",) or (state == "hold" and self.pacer.held):
            return "STATUS, BUSY"
        word = {"hold": "FEED HOLD", "alarm": "ALARM ON"}.get(state, "IDLE")
        return f"PROGRAM, O09100, {word}, PARTS, {self.starts}"

    # ------------------------------------------------------------------ the wire
    def _answer(self, line: str) -> str:
        self.requests.append(line)
        if line == "?Q100":
            return "SERIAL NUMBER, 1234567"
        if line == "?Q101":
            return "SOFTWARE VERSION, 100.23.000.1012"
        if line == "?Q102":
            return "MODEL, UMC-750"
        if line == "?Q104":
            return "MODE, MEM"
        if line == "?Q500":
            return self._status()
        m = _Q600.fullmatch(line)
        if m:
            n = int(m.group(1)) - self.base
            return f"MACRO, {self._var(n):.6f}" if n >= 1 else "?"
        m = _E.fullmatch(line)
        if m:
            n = int(m.group(1)) - self.base
            if not any(lo <= n <= hi for lo, hi in WRITABLE):
                return "?"
            self.ctrl.variables[f"#{n}"] = float(m.group(2))
            return "!"
        return "?"

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self._writers) >= MAX_CLIENTS:
            writer.transport.abort()
            return
        self._writers.add(writer)
        try:
            while True:
                raw = await reader.readuntil(b"\n")
                line = raw.decode("ascii", errors="replace").strip()
                if not line:
                    continue
                answer = frame(self._answer(line))
                for w in list(self._writers):  # every answer to every connection
                    with contextlib.suppress(ConnectionError, RuntimeError):
                        w.write(answer)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            pass
        finally:
            self._writers.discard(writer)
            writer.close()
