"""SINUMERIK OPC UA link: the control's own OPC UA server, as Siemens ships it (Access MyMachine /
OPC UA). The part program is written through the server's file system ("Part Programs", OPC UA
Part 5 FileType) and selected with the server's ``Select`` method; the control offers no NC start,
so the machine starts it (its PLC on the start request, or the operator) and the link says so in
the run's status. Results come back through R parameters the program writes (the Siemens
dialect's ring R100-R187 and counter R99) with the R188 ack / R189 stop handshake; the
start-of-shift request, busy, done, verdict and program-ready flags are R parameters or GUDs the
shop declares (``nodes:``).

Address space and sources: contracts/sinumerik_space.py, drivers/README.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator
from typing import Any

from asyncua import ua

from contracts.jobs import ProgramJob, Verdict
from contracts.messages import ProbeHit
from contracts.result_lines import HANDSHAKE_VARIABLES, RESULT_COUNTERS, SLOT_FIELDS
from contracts.sinumerik_space import (
    ACTIVE_PROGRAM,
    FILE_SYSTEM,
    HANDSHAKE_ROLES,
    HELD_PROGRAM,
    METHODS,
    PROG_STATUS,
    PROGRAM_FOLDERS,
    SELECT,
    file_name,
    r_number,
    select_path,
)
from contracts.temperatures import TemperatureChannel
from drivers.base import (
    Capabilities,
    CncLink,
    ControllerAborted,
    ControllerAlarm,
    LinkError,
    StartRequest,
)
from drivers.hits import HitFactory, MalformedResult
from drivers.retry import wait_event, with_backoff
from drivers.sinumerik.client import Fatal, SinumerikSession, finite
from drivers.sinumerik.schema import SinumerikLinkConfig
from drivers.variable_ring import check_counter, decode, number, slot_numbers

log = logging.getLogger("rumba.sinumerik")
POLL_S = 0.2  # re-read when no notification arrives (a lost publish, a reconnect)
COUNTER = r_number(RESULT_COUNTERS["siemens"])
ACK, STOP = (r_number(v) for v in HANDSHAKE_VARIABLES["siemens"])
RING_BASE = COUNTER + 1  # R100: the Siemens dialect's first slot variable
STATE_ROLES = ("prog_status", "chan_status", "selected_program")


class _Wake:
    """Data-change notifications only wake the link up; it reads what it needs itself."""

    def __init__(self, event: asyncio.Event) -> None:
        self.event = event

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.event.set()

    def status_change_notification(self, status: Any) -> None:
        self.event.set()


class SinumerikLink(CncLink):
    capabilities = Capabilities(start_request=True, streams_blocks=False, loads_program=True,
                                writes_verdict=True, can_abort=True)
    handshake = True

    def __init__(self, cfg: SinumerikLinkConfig) -> None:
        self.cfg = cfg
        self.start_timeout_s = cfg.nc_start_timeout_s
        self._s = SinumerikSession(cfg)
        self._wake = asyncio.Event()
        self._sub: Any = None
        self._folder: Any = None
        self._methods: Any = None
        self._select: Any = None
        self._connected_once = False
        self._stop_asked = False

    @property
    def where(self) -> str:
        return f"sinumerik {self.cfg.url}"

    # ------------------------------------------------------------------ connection
    async def connect(self) -> None:
        if self._s.client is not None:
            return
        try:
            await with_backoff(self._s.open, what=self.where,
                               timeout_s=self.cfg.connect_timeout_s,
                               refused_is_final=not self._connected_once)
        except Fatal as e:
            raise LinkError(str(e)) from None
        try:
            await self._s.check_roles(HANDSHAKE_ROLES + STATE_ROLES)
            for n in (COUNTER, ACK, STOP, RING_BASE + SLOT_FIELDS * 8 - 1):
                if finite(await self._s.r_param(n).read_value()) is None:
                    raise LinkError(f"{self.where}: R{n} is not a Double: the control must "
                                    "hold R0-R189 (MD28050 MM_NUM_R_PARAM >= 190)")
            self._folder = await self._s.browse(*FILE_SYSTEM, PROGRAM_FOLDERS[0])
            self._methods = await self._s.browse(*METHODS)
            self._select = await self._s.browse(*METHODS, SELECT)
            client = self._s.client
            assert client is not None
            self._sub = await client.create_subscription(100, _Wake(self._wake))
            await self._sub.subscribe_data_change([self._s.role("request"),
                                                   self._s.r_param(COUNTER),
                                                   self._s.role("prog_status")])
        except (LinkError, ua.UaError, OSError, ConnectionError) as e:
            await self._s.close()
            raise LinkError(str(e) if isinstance(e, LinkError)
                            else f"{self.where}: address space: {e}") from None
        self._connected_once = True

    async def close(self) -> None:
        self._sub = None
        await self._s.close()

    async def _read(self, nodes: list[Any], what: str) -> list[Any]:
        """A read that rides out a connection drop: asyncua reconnects in the background and
        the results wait in the ring (the program waits while it is full)."""
        deadline = time.monotonic() + self.cfg.connect_timeout_s
        while True:
            try:
                return await self._s.read(nodes, what)
            except LinkError:
                if self._s.client is None or time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.2)

    async def _sleep_for_change(self, timeout_s: float) -> None:
        self._wake.clear()
        await wait_event(self._wake, timeout_s)

    # ------------------------------------------------------------------ handshake
    async def wait_start_request(self) -> StartRequest:
        """Wait for REQUEST = 1 with DONE = 0; answer BUSY = 1. DONE and VERDICT are cleared
        once REQUEST drops."""
        while True:
            request, done = await self._read([self._s.role("request"), self._s.role("done")],
                                             "request, done")
            request, done = finite(request) or 0.0, finite(done) or 0.0
            if done >= 0.5 and request < 0.5:
                await self._s.write_double(self._s.role("done"), 0.0, "done")
                await self._s.write_double(self._s.role("verdict"), 0.0, "verdict")
                done = 0.0
            if request >= 0.5 and done < 0.5:
                await self._s.write_double(self._s.role("busy"), 1.0, "busy")
                return StartRequest(source="cnc",
                                    detail=f"{self._s.node_id('request')} = 1")
            await self._sleep_for_change(0.5)

    async def write_verdict(self, verdict: Verdict) -> None:
        await self._s.write_double(self._s.role("verdict"), float(verdict.code), "verdict")
        await self._s.write_double(self._s.role("done"), 1.0, "done")
        await self._s.write_double(self._s.role("busy"), 0.0, "busy")
        await self._s.write_double(self._s.role("program_ready"), 0.0, "program_ready")

    async def read_temperature(self, channel: TemperatureChannel) -> float:
        nid = (channel.address if channel.address.startswith("ns=")
               else f"ns={self._s.ns};s={channel.address}")
        try:
            (value,) = await self._s.read([self._s._client().get_node(nid)],
                                          f"temperature {channel.name}")
        except ValueError as e:
            raise LinkError(f"{self.where}: temperature {channel.name} ({nid}): {e}") from None
        v = finite(value)
        if v is None:
            raise LinkError(f"{self.where}: temperature {channel.name} ({nid}) = {value!r}, "
                            "not a finite number")
        return v * channel.scale + channel.offset_c

    # ------------------------------------------------------------------ program
    async def _prog_status(self) -> int:
        (value,) = await self._read([self._s.role("prog_status")], "progStatus")
        return int(number(value, self._s.node_id("prog_status"), "program state",
                          integer=True))

    async def _load(self, job: ProgramJob) -> str:
        """Write, then select the program; the ring's counter, ack and stop cleared first (the
        counter a previous run left must not read as this run's touches)."""
        if job.dialect != "siemens":
            raise LinkError(f"{self.where}: the SINUMERIK profile runs Siemens programs, not "
                            f"{job.dialect} (daemon.yaml dialect: siemens)")
        if f"R{COUNTER}-R{ACK}>=" not in job.text:
            raise LinkError(f"{self.where}: the program carries no result handshake "
                            f"(R{ACK}/R{STOP}): generated for another transport")
        state = await self._prog_status()
        if state in ACTIVE_PROGRAM or state in HELD_PROGRAM:
            raise LinkError(f"{self.where}: channel {self.cfg.channel} is busy (program "
                            f"{PROG_STATUS.get(state, state)}): not loading a program now")
        for n in (COUNTER, ACK, STOP):
            await self._s.write_double(self._s.r_param(n), 0.0, f"R{n}")
        name = self.cfg.program_name
        await self._s.upload(self._folder, file_name(name), job.text)
        path = select_path(name)
        await self._s.call(self._methods, self._select, (path, self.cfg.channel),
                           f"{SELECT}({path}, channel {self.cfg.channel})")
        return path

    async def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        if self._s.client is None:
            raise LinkError(f"{self.where}: not connected")
        self._stop_asked = False
        path = await self._load(job)
        await self._s.write_double(self._s.role("program_ready"), 1.0, "program_ready")
        self.say_step(f"while waiting for NC start at the machine: program "
                      f"{file_name(self.cfg.program_name)} selected in channel "
                      f"{self.cfg.channel}, the machine's PLC starts it on the start request "
                      "or the operator presses NC start (the control offers no remote start)")
        selected = time.monotonic()
        hits: HitFactory | None = None
        last = got = 0
        progress_t = held_t = time.monotonic()
        total = job.touch_count
        try:
            while True:
                counter, state = await self._read([self._s.r_param(COUNTER),
                                                   self._s.role("prog_status")],
                                                  f"R{COUNTER}, progStatus")
                state = int(number(state, self._s.node_id("prog_status"), "program state",
                                   integer=True))
                if hits is None:
                    if state not in ACTIVE_PROGRAM and not (finite(counter) or 0):
                        if time.monotonic() - selected > self.cfg.nc_start_timeout_s:
                            raise LinkError(f"no NC start within {self.cfg.nc_start_timeout_s:g}"
                                            f" s of selecting {path}")
                        await self._sleep_for_change(POLL_S)
                        continue
                    hits = HitFactory(job)  # the program runs: the run's clock starts
                    self.say_step(None)
                    await self._started(path)
                    progress_t = time.monotonic()
                try:
                    n = check_counter(counter, f"R{COUNTER}", last, total or None)
                    if n > last:
                        async for hit in self._slots(hits, last, n):
                            last, got = hit.seq, got + 1
                            yield hit
                            if not hit.triggered:
                                raise ControllerAlarm(
                                    f"probe did not trigger at touch seq {hit.seq}")
                        progress_t = time.monotonic()
                        continue  # more may have arrived meanwhile
                except MalformedResult:
                    await self._stop_quietly()
                    raise
                if state not in ACTIVE_PROGRAM and state not in HELD_PROGRAM:
                    # ended: one more read of the counter (written just before the end)
                    (counter,) = await self._read([self._s.r_param(COUNTER)], f"R{COUNTER}")
                    if check_counter(counter, f"R{COUNTER}", last, total or None) > last:
                        continue
                    if got == total:
                        return
                    if self._stop_asked:
                        raise LinkError(f"the program ended at rumba's stop request after "
                                        f"{got} of {total} touches")
                    raise ControllerAborted(f"program ended on the controller after {got} of "
                                            f"{total} touches (RESET or an alarm there)")
                now = time.monotonic()
                if state in HELD_PROGRAM:
                    if now - held_t >= self.cfg.result_timeout_s:
                        raise LinkError(f"program {PROG_STATUS[state]} on the control for "
                                        f"{self.cfg.result_timeout_s:g} s (NC stop, M0 or an "
                                        f"alarm there), {got} of {total} touches")
                else:
                    held_t = now
                if now - progress_t >= self.cfg.result_timeout_s:
                    raise LinkError(f"no touch result for {self.cfg.result_timeout_s:g} s "
                                    f"(program {PROG_STATUS.get(state, state)}, {got} of "
                                    f"{total} touches)")
                await self._sleep_for_change(POLL_S)
        finally:
            self.say_step(None)

    async def _started(self, path: str) -> None:
        """The program runs: the PLC's flag dropped, and it must be ours (another program
        started at the machine would feed this run someone else's R parameters)."""
        with contextlib.suppress(LinkError):
            await self._s.write_double(self._s.role("program_ready"), 0.0, "program_ready")
        (selected,) = await self._read([self._s.role("selected_program")], "selected program")
        if isinstance(selected, str) and selected and selected.upper() != path.upper():
            await self._stop_quietly()
            raise LinkError(f"{self.where}: the channel runs {selected!r}, not rumba's {path}")

    async def _slots(self, hits: HitFactory, last: int, counter: int
                     ) -> AsyncIterator[ProbeHit]:
        """Touches last+1 … counter from their slots, then the ack (frees the slots)."""
        for n in range(last + 1, counter + 1):
            numbers = slot_numbers(RING_BASE, n)
            values = await self._read([self._s.r_param(k) for k in numbers],
                                      f"R{numbers[0]}-R{numbers[-1]}")
            yield decode(hits, values, [f"R{k}" for k in numbers], n,
                         f"slot R{numbers[0]}-R{numbers[-1]}, touch counter {n}")
        with contextlib.suppress(LinkError):  # written again with the next batch anyway
            await self._s.write_double(self._s.r_param(ACK), float(counter), f"R{ACK}")

    async def abort(self) -> None:
        """Ask the program to end (R189 = 1: it ends at its next touch with M30, no alarm to
        acknowledge; a program not yet started ends at once when started) and wait until it
        has; ``LinkError`` when it does not (stopped at the machine: press RESET there)."""
        if self._s.client is None:
            raise LinkError(f"{self.where}: not connected: the program was not stopped")
        self._stop_asked = True
        await self._s.write_double(self._s.r_param(STOP), 1.0, f"R{STOP}")
        with contextlib.suppress(LinkError):
            await self._s.write_double(self._s.role("program_ready"), 0.0, "program_ready")
        deadline = time.monotonic() + self.cfg.stop_timeout_s
        while True:
            state = await self._prog_status()
            if state not in ACTIVE_PROGRAM and state not in HELD_PROGRAM:
                return
            if time.monotonic() > deadline:
                raise LinkError(f"the program did not end within {self.cfg.stop_timeout_s:g} s"
                                f" of the stop request (program {PROG_STATUS.get(state, state)}"
                                "): press RESET at the machine")
            await self._sleep_for_change(POLL_S)

    async def _stop_quietly(self) -> None:
        with contextlib.suppress(LinkError):
            await self.abort()
