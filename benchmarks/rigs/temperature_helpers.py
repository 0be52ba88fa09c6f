"""One run started from the simulated CNC with temperature channels: the daemon's Service up, the
start request raised on the control, the verdict awaited there, the run's journal rows read back
(tests/test_temperature_channels.py, _dnc_dialects.py, _silent.py, _reprobe.py); a Modbus TCP
transmitter that falls silent, on a real loopback socket (_silent.py, _abort.py); a run's
recorder of one channel on a real journal (_abort.py, _end_abort.py)."""

from __future__ import annotations

import asyncio
import contextlib
import struct
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchmarks.rigs.e2e_run import RUN_TIMEOUT_S, wait_verdict_on_cnc
from contracts.temperatures import TemperatureChannel, TemperatureReading
from daemon.config import DaemonConfig
from daemon.run.temperatures import TemperatureRecorder
from daemon.service.service import Service
from daemon.store.journal import Store
from daemon.store.temperatures import temperatures
from simulators.controller import VirtualController


@dataclass
class CncRun:
    """What one run left: its session (state, reason) and its journal rows."""

    session: Any
    run_id: str
    readings: list[TemperatureReading]
    analysis: Any
    verdict: dict[str, Any] | None
    report: tuple[Path, Path] | None


async def run_from_cnc(cfg: DaemonConfig, ctrl: VirtualController,
                       machine: str = "mill1",
                       before: Callable[[Any], None] | None = None) -> CncRun:
    """Start the Service on ``cfg``, raise the start request on ``ctrl``, wait for the verdict on
    the CNC (a failed run raises at once with its reason), read the run's rows, stop;
    ``before``: called with the machine's session before the request (e.g. to watch its link)."""
    service = Service(cfg)
    await service.start()
    try:
        session = service.sessions[machine]
        if before is not None:
            before(session)
        ctrl.raise_start_request()
        await wait_verdict_on_cnc(session, ctrl, RUN_TIMEOUT_S)
        run_id = session.run_id
        store = service.store
        return CncRun(session, run_id, temperatures(store, run_id), store.analysis(run_id),
                      store.verdict(run_id), store.report(run_id))
    finally:
        await service.stop()


@dataclass
class SilentTransmitter:
    """Accepts Modbus TCP connections, reads the requests and answers only the first
    ``answer_first`` of them (then never again: switched off behind a live switch port)."""

    answer_first: int = 0
    connections: int = 0
    requests: int = 0
    request_seen: asyncio.Event = field(default_factory=asyncio.Event)
    _writers: list[asyncio.StreamWriter] = field(default_factory=list)
    _tasks: list[asyncio.Task] = field(default_factory=list)

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        self._writers.append(writer)
        self._tasks.append(asyncio.current_task())  # type: ignore[arg-type]
        with contextlib.suppress(ConnectionError, asyncio.IncompleteReadError):
            while True:
                head = await reader.readexactly(7)  # MBAP: transaction, protocol, length, unit
                tid, _, length, unit = struct.unpack(">HHHB", head)
                pdu = await reader.readexactly(length - 1)
                self.requests += 1
                self.request_seen.set()
                if self.requests <= self.answer_first:  # 23.5 °C at 0.1 °C per count
                    count = struct.unpack(">H", pdu[3:5])[0]
                    body = bytes([pdu[0], 2 * count]) + struct.pack(">H", 235) * count
                    writer.write(struct.pack(">HHHB", tid, 0, len(body) + 1, unit) + body)
                    await writer.drain()

    async def close(self) -> None:
        for w in self._writers:
            w.transport.abort()
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

@contextlib.asynccontextmanager
async def silent_transmitter(answer_first: int = 0
                             ) -> AsyncIterator[tuple[SilentTransmitter, int]]:
    """A ``SilentTransmitter`` listening on a free loopback port: (it, the port); its
    connections and the server closed on leaving."""
    tx = SilentTransmitter(answer_first)
    server = await asyncio.start_server(tx.handle, "127.0.0.1", 0)
    try:
        yield tx, server.sockets[0].getsockname()[1]
    finally:
        await tx.close()
        server.close()
        await server.wait_closed()


def column(port: int, timeout_s: float = 1.0) -> dict:
    return {"name": "column", "source": "transmitter", "address": "input:0", "scale": 0.1,
            "transmitter": {"host": "127.0.0.1", "port": port, "timeout_s": timeout_s}}


async def fleet_against(http: Any, url: str, machine: str, channel: str = "spindle",
                        link: str = "EX0C") -> dict[str, Any]:
    """The fleet page's link-against-temperature API for ``machine`` over ``http`` (an
    aiohttp session signed in), its answer asserted 200."""
    async with http.get(f"{url}/api/machines/{machine}/temperature",
                        params={"channel": channel, "link": link}) as r:
        got = await r.json()
        assert r.status == 200, got
    return got


@contextlib.asynccontextmanager
async def one_channel_recorder(path: Path, link: Any
                               ) -> AsyncIterator[tuple[Store, TemperatureRecorder]]:
    """Run r1's recorder of one OPC UA channel read through ``link`` (a test's link that holds
    its reads), on a real journal at ``path``; closed after the test."""
    store = Store(path)
    store.new_run("r1", "mill1", "test")
    ch = TemperatureChannel(name="spindle", address="/Channel/Temperatures/Z")
    rec = TemperatureRecorder("mill1", (ch,), link=link, store=store, link_name="opcua")
    try:
        yield store, rec
    finally:
        await rec.close()
        store.close()
