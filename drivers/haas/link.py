"""Haas NGC link over its Ethernet data port (Machine Data Collection): the program goes to the
machine's network share (``program_dir``: O09100.nc), the operator (or the shop's start-of-shift
routine) runs it — the data port starts nothing, and the link says so in the run's status —
and results, the handshake, the stop and the verdict are macro variables read with ``?Q600`` and
written with ``?E``: the Haas dialect's ring #600-#687 and counter #599 with the #688 ack and the
#689 stop (``contracts.result_lines.HANDSHAKE_VARIABLES``), the verdict #598, the start-of-shift
request #690, busy #691, done #692, program-ready #693 (``variables:`` moves the last four).
On NGC every user variable is read and written at its NGC number (legacy #n → #10000 + n,
``variable_base``)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import AsyncIterator

from contracts.jobs import ProgramJob, Verdict
from contracts.messages import ProbeHit
from contracts.result_lines import HANDSHAKE_VARIABLES, RESULT_COUNTERS, VERDICT_VARIABLES
from contracts.temperatures import TemperatureChannel
from drivers.base import (
    Capabilities,
    CncLink,
    ControllerAborted,
    ControllerAlarm,
    LinkError,
    StartRequest,
)
from drivers.haas.port import DataPort
from drivers.haas.schema import HaasLinkConfig
from drivers.hits import HitFactory, MalformedResult
from drivers.retry import with_backoff
from drivers.variable_ring import check_counter, decode, slot_numbers

log = logging.getLogger("rumba.haas")
COUNTER = int(RESULT_COUNTERS["haas"][1:])
ACK, STOP = (int(v[1:]) for v in HANDSHAKE_VARIABLES["haas"])
VERDICT = int(VERDICT_VARIABLES["haas"][1:])
RING_BASE = COUNTER + 1  # #600
PROGRAM_FILE = "O09100.nc"  # the Haas dialect's O9100 on the share


class HaasLink(CncLink):
    capabilities = Capabilities(start_request=True, streams_blocks=False, loads_program=True,
                                writes_verdict=True, can_abort=True)
    handshake = True

    def __init__(self, cfg: HaasLinkConfig) -> None:
        self.cfg = cfg
        self.start_timeout_s = cfg.nc_start_timeout_s
        self._port = DataPort(cfg.host, cfg.port, cfg.request_timeout_s)
        self._connected_once = False
        self._stop_asked = False

    def _n(self, legacy: int) -> int:
        """The number the data port knows variable #legacy by."""
        return self.cfg.variable_base + legacy

    async def _read(self, legacy: int) -> float:
        return await self._port.read(self._n(legacy))

    async def _write(self, legacy: int, value: float) -> None:
        await self._port.write(self._n(legacy), value)

    # ------------------------------------------------------------------ connection
    async def _open(self) -> None:
        await self._port.connect()
        try:
            answer = await self._port.request("?Q100")
            if not answer.upper().startswith("SERIAL NUMBER"):
                raise LinkError(f"{self._port.where}: ?Q100 answered {answer[:40]!r}: not a "
                                "Haas data port (Setting 143)")
            await self._read(COUNTER)  # the numbering (variable_base) works
        except BaseException:
            await self._port.close()
            raise

    async def connect(self) -> None:
        if self._port.open:
            return
        await with_backoff(self._open, what=self._port.where,
                           timeout_s=self.cfg.connect_timeout_s,
                           refused_is_final=not self._connected_once)
        self._connected_once = True

    async def close(self) -> None:
        await self._port.close()

    # ------------------------------------------------------------------ handshake
    async def wait_start_request(self) -> StartRequest:
        request, done = self.cfg.variable("request"), self.cfg.variable("done")
        while True:
            if not self._port.open:
                await self.connect()
            r, d = await self._read(request), await self._read(done)
            if d >= 0.5 and r < 0.5:
                await self._write(done, 0.0)
                await self._write(VERDICT, 0.0)
                d = 0.0
            if r >= 0.5 and d < 0.5:
                await self._write(self.cfg.variable("busy"), 1.0)
                return StartRequest(source="cnc", detail=f"#{self._n(request)} = 1")
            await asyncio.sleep(max(self.cfg.poll_interval_s, 0.2))

    async def write_verdict(self, verdict: Verdict) -> None:
        await self._write(VERDICT, float(verdict.code))
        await self._write(self.cfg.variable("done"), 1.0)
        await self._write(self.cfg.variable("busy"), 0.0)
        await self._write(self.cfg.variable("program_ready"), 0.0)

    async def read_temperature(self, channel: TemperatureChannel) -> float:
        value = await self._read(int(channel.address[1:]))
        return value * channel.scale + channel.offset_c

    # ------------------------------------------------------------------ program
    def _put_program(self, text: str) -> str:
        """O09100.nc onto the share, atomically (a machine never reads half a program)."""
        folder = self.cfg.program_dir
        if not folder.is_dir():
            raise LinkError(f"program_dir {folder}: not a folder (the machine's network "
                            "share, mounted here)")
        path = folder / PROGRAM_FILE
        tmp = folder / f".{PROGRAM_FILE}.rumba-tmp"
        try:
            tmp.write_text(text, encoding="ascii", newline="\r\n")
            os.replace(tmp, path)
        except (OSError, UnicodeEncodeError) as e:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise LinkError(f"{path}: not written ({e})") from None
        return str(path)

    async def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        if not self._port.open:
            raise LinkError(f"{self._port.where}: not connected")
        if job.dialect != "haas":
            raise LinkError(f"{self._port.where}: the Haas data port link runs Haas programs "
                            f"(dialect haas), not {job.dialect}")
        if f"#{COUNTER}-#{ACK}GE" not in job.text:
            raise LinkError(f"{self._port.where}: the program carries no result handshake "
                            f"(#{ACK}/#{STOP}): generated for another transport")
        state, _ = await self._port.status()
        if state == "BUSY":
            raise LinkError(f"{self._port.where}: a program runs on the control: not loading "
                            "one now")
        self._stop_asked = False
        for n in (COUNTER, ACK, STOP):
            await self._write(n, 0.0)
        path = await asyncio.to_thread(self._put_program, job.text)
        await self._write(self.cfg.variable("program_ready"), 1.0)
        self.say_step(f"while waiting for cycle start at the machine: {path} on the share "
                      "(O09100), the operator or the shop's start-of-shift routine runs it "
                      "(the data port starts no program)")
        sent = time.monotonic()
        hits: HitFactory | None = None
        last = 0
        total = job.touch_count
        progress_t = held_t = time.monotonic()
        try:
            while True:
                counter = await self._read(COUNTER)
                state, _ = await self._port.status()
                if hits is None:
                    if state != "BUSY" and not counter:
                        if time.monotonic() - sent > self.cfg.nc_start_timeout_s:
                            raise LinkError(f"no cycle start within "
                                            f"{self.cfg.nc_start_timeout_s:g} s")
                        await asyncio.sleep(self.cfg.poll_interval_s)
                        continue
                    hits = HitFactory(job)
                    self.say_step(None)
                    with contextlib.suppress(LinkError):
                        await self._write(self.cfg.variable("program_ready"), 0.0)
                try:
                    n = check_counter(counter, f"#{self._n(COUNTER)}", last, total or None)
                    if n > last:
                        for k in range(last + 1, n + 1):
                            hit = await self._slot(hits, k)
                            last = k
                            progress_t = time.monotonic()
                            yield hit
                            if not hit.triggered:
                                raise ControllerAlarm(f"probe did not trigger at touch seq {k}")
                        with contextlib.suppress(LinkError):
                            await self._write(ACK, float(n))
                        continue
                except MalformedResult:
                    await self._stop_quietly()
                    raise
                if state != "BUSY":
                    if last == total and "ALARM" not in state:
                        return
                    if self._stop_asked:
                        raise LinkError(f"the program ended at rumba's stop request after "
                                        f"{last} of {total} touches")
                    if "ALARM" in state:
                        raise ControllerAlarm(f"alarm on the control after {last} of {total} "
                                              "touches")
                    if state == "IDLE":
                        raise ControllerAborted(f"program ended on the control after {last} "
                                                f"of {total} touches (RESET there)")
                now = time.monotonic()
                if state not in ("BUSY", "IDLE"):  # feed hold, a stop …
                    if now - held_t >= self.cfg.result_timeout_s:
                        raise LinkError(f"program {state.lower()} on the control for "
                                        f"{self.cfg.result_timeout_s:g} s")
                else:
                    held_t = now
                if now - progress_t >= self.cfg.result_timeout_s:
                    raise LinkError(f"no touch result for {self.cfg.result_timeout_s:g} s "
                                    f"({last} of {total} touches)")
                await asyncio.sleep(self.cfg.poll_interval_s)
        finally:
            self.say_step(None)

    async def _slot(self, hits: HitFactory, n: int) -> ProbeHit:
        numbers = slot_numbers(RING_BASE, n)
        values = [await self._read(k) for k in numbers]
        names = [f"#{self._n(k)}" for k in numbers]
        return decode(hits, values, names, n, f"slot {names[0]}-{names[-1]}, counter {n}")

    async def abort(self) -> None:
        """#689 = 1: the program ends (M30) at its next touch; one not started yet ends at its
        first. Waits until the control is no longer busy."""
        if not self._port.open:
            raise LinkError(f"{self._port.where}: not connected: the program was not stopped")
        self._stop_asked = True
        await self._write(STOP, 1.0)
        with contextlib.suppress(LinkError):
            await self._write(self.cfg.variable("program_ready"), 0.0)
        deadline = time.monotonic() + self.cfg.stop_timeout_s
        while True:
            state, _ = await self._port.status()
            if state in ("IDLE",) or "ALARM" in state:
                return
            if time.monotonic() > deadline:
                raise LinkError(f"the program did not end within {self.cfg.stop_timeout_s:g} s "
                                f"of the stop request ({state.lower()}): RESET at the machine")
            await asyncio.sleep(self.cfg.poll_interval_s)

    async def _stop_quietly(self) -> None:
        with contextlib.suppress(LinkError):
            await self.abort()
