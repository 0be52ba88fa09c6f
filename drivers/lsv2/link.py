"""LSV2 link: a HEIDENHAIN TNC as shipped, over its LSV2 port (TNCremo's protocol), with pylsv2.

The program (RUMBA.H), its FN 16 format files, the stop program and the verdict program are
written into one folder on the TNC (``directory``); the TNC offers no remote NC start over LSV2,
so the operator (or the machine's PLC) starts RUMBA.H and the link says so in the run's status.
The program appends one result line per touch with FN 16 F-PRINT to RUMBA_RES.TXT next to it;
the link reads that file as it grows (R_FL) and the program state (R_RI, DNC login) until the
program has finished. Before each touch the program calls RUMBASTP.H and ends when it sets
Q1689 = 1: rumba's stop writes it (LSV2 writes files, not Q parameters). The verdict is the
program RUMBAV.H (Q1598 = code) the shop's programs call. The start-of-shift request is the file
RUMBA_REQ.TXT the shop's start-of-shift program prints (``RUMBA REQUEST <machine>``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator

from contracts.jobs import DialectCodec, ProgramJob, Verdict
from contracts.messages import ProbeHit
from contracts.result_lines import STOP_PROGRAMS
from drivers.base import (
    Capabilities,
    CncLink,
    ControllerAborted,
    ControllerAlarm,
    LinkError,
    StartRequest,
)
from drivers.hits import HitFactory
from drivers.lsv2.client import Lsv2Session
from drivers.lsv2.schema import Lsv2LinkConfig
from drivers.retry import with_backoff
from drivers.serial.lines import parse_request

log = logging.getLogger("rumba.lsv2")
STOP_PROGRAM, STOP_VAR = STOP_PROGRAMS["heidenhain"]
PROGRAM, RESULTS, REQUEST, VERDICT = "RUMBA.H", "RUMBA_RES.TXT", "RUMBA_REQ.TXT", "RUMBAV.H"
# pylsv2 PgmState: the TNC's state of the selected program
STARTED, STOPPED, FINISHED, CANCELLED, INTERRUPTED, ERROR = 0, 1, 2, 3, 4, 5
STATE_NAMES = {0: "started", 1: "stopped", 2: "finished", 3: "cancelled", 4: "interrupted",
               5: "error", 6: "error cleared", 7: "idle", 8: "undefined"}


def stop_program(stop: bool) -> str:
    """RUMBASTP.H: ``Q1689 = +1`` ends the program at its next touch (only 0/1 reach it)."""
    return (f"0 BEGIN PGM RUMBASTP MM\n1 {STOP_VAR} = +{int(bool(stop))}\n"
            "2 END PGM RUMBASTP MM\n")


NO_VERDICT = "0 BEGIN PGM RUMBAV MM\n1 Q1598 = +0\n2 END PGM RUMBAV MM\n"
"""RUMBAV.H while a run goes on: no verdict yet (the codes 1-4 are the dialect's program)."""


class Lsv2Link(CncLink):
    capabilities = Capabilities(start_request=True, streams_blocks=False, loads_program=True,
                                writes_verdict=True, can_abort=True)
    handshake = True
    uses_dialect = True

    def __init__(self, cfg: Lsv2LinkConfig, dialect: DialectCodec | None = None) -> None:
        self.cfg = cfg
        self.dialect = dialect
        self.start_timeout_s = cfg.nc_start_timeout_s
        self._s = Lsv2Session(cfg)
        self._connected_once = False
        self._stop_asked = False

    def _path(self, name: str) -> str:
        return f"{self.cfg.directory}\\{name}"

    # ------------------------------------------------------------------ connection
    async def connect(self) -> None:
        if self._s.con is not None:
            return
        await with_backoff(self._s.open, what=self._s.where,
                           timeout_s=self.cfg.connect_timeout_s,
                           refused_is_final=not self._connected_once)
        self._connected_once = True

    async def close(self) -> None:
        await self._s.close()

    def __del__(self) -> None:  # the worker thread and the temporary folder
        with contextlib.suppress(Exception):
            self._s.shutdown()

    # ------------------------------------------------------------------ handshake
    async def wait_start_request(self) -> StartRequest:
        """The request file the start-of-shift program printed: read, deleted, then parsed
        (a broken line is logged and dropped: a request is never guessed)."""
        path = self._path(REQUEST)
        while True:
            if self._s.con is None:
                await self.connect()
            if await self._s.exists(path) is not None:
                text = await self._s.get(path)
                await self._s.delete(path)
                for line in text.splitlines():
                    try:
                        machine = parse_request(line)
                    except ValueError as e:
                        log.warning("%s: %s", path, e)
                        continue
                    if machine is None:
                        continue
                    want = self.cfg.request_machine
                    if want is not None and machine.lower() != want.lower():
                        log.warning("%s: request for machine %s ignored (this link serves %s)",
                                    path, machine, want)
                        continue
                    return StartRequest(source="cnc", machine=machine, detail=path)
            await asyncio.sleep(max(self.cfg.poll_interval_s, 1.0))

    async def write_verdict(self, verdict: Verdict) -> None:
        """RUMBAV.H with Q1598 = code (the dialect's verdict program: only the code 1-4)."""
        if self.dialect is None:
            raise LinkError("no dialect known for the verdict program")
        try:
            text = self.dialect.verdict_program(verdict.code)
        except ValueError as e:
            raise LinkError(str(e)) from None
        await self._s.put(self._path(VERDICT), text)

    # ------------------------------------------------------------------ program
    async def _load(self, job: ProgramJob) -> None:
        if job.dialect != "heidenhain":
            raise LinkError(f"{self._s.where}: LSV2 runs TNC programs (dialect heidenhain), "
                            f"not {job.dialect}")
        if f"CALL PGM {STOP_PROGRAM}" not in job.text:
            raise LinkError(f"{self._s.where}: the program does not call {STOP_PROGRAM}: "
                            "generated for another transport")
        state = await self._s.program_state()
        if state in (STARTED, STOPPED, INTERRUPTED):
            raise LinkError(f"{self._s.where}: a program is {STATE_NAMES[state]} on the TNC: "
                            "not loading one now")
        await self._s.ensure_directory(self.cfg.directory)
        if await self._s.exists(self._path(RESULTS)) is not None:
            await self._s.delete(self._path(RESULTS))
        await self._s.put(self._path(STOP_PROGRAM), stop_program(False))
        await self._s.put(self._path(VERDICT), NO_VERDICT)
        for name, text in sorted(job.files.items()):
            await self._s.put(self._path(name), text)
        await self._s.put(self._path(PROGRAM), job.text)

    async def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        if self._s.con is None:
            raise LinkError(f"{self._s.where}: not connected")
        codec = job.codec or self.dialect
        if codec is None:
            raise LinkError(f"no result decoder for the {job.dialect} program")
        if job.codec is not None:
            self.dialect = job.codec
        self._stop_asked = False
        await self._load(job)
        program = self._path(PROGRAM)
        self.say_step(f"while waiting for NC start at the machine: {program} transferred, the "
                      "operator selects it in Program Run and presses NC start (LSV2 starts "
                      "no program)")
        sent = time.monotonic()
        hits: HitFactory | None = None
        lines_done = size_done = 0
        total = job.touch_count
        progress_t = held_t = time.monotonic()
        try:
            while True:
                state = await self._s.program_state()
                size = await self._s.exists(self._path(RESULTS))
                if hits is None:
                    if state != STARTED and not size:
                        if time.monotonic() - sent > self.cfg.nc_start_timeout_s:
                            raise LinkError(f"no NC start within "
                                            f"{self.cfg.nc_start_timeout_s:g} s of sending "
                                            f"{program}")
                        await asyncio.sleep(self.cfg.poll_interval_s)
                        continue
                    hits = HitFactory(job)
                    self.say_step(None)
                    selected = await self._s.selected_program()
                    if selected and selected.upper() != program.upper():
                        raise LinkError(f"{self._s.where}: the TNC runs {selected}, not "
                                        f"rumba's {program}")
                if size and size != size_done:
                    text = await self._s.get(self._path(RESULTS))
                    size_done = size
                    lines = [ln for ln in text.splitlines() if ln.strip()]
                    for line in lines[lines_done:]:
                        lines_done += 1
                        hit = self._decode(codec, hits, line)
                        if hit is None:
                            continue
                        progress_t = time.monotonic()
                        yield hit
                        if not hit.triggered:
                            raise ControllerAlarm(f"probe did not trigger at touch seq "
                                                  f"{hit.seq}")
                    continue  # read the state again: the file may have grown meanwhile
                if state in (FINISHED, CANCELLED, ERROR):
                    if hits.made == total and state == FINISHED:
                        return
                    if self._stop_asked:
                        raise LinkError(f"the program ended at rumba's stop request after "
                                        f"{hits.made} of {total} touches")
                    if state == ERROR:
                        raise ControllerAlarm(f"the TNC stopped the program with an error "
                                              f"after {hits.made} of {total} touches")
                    if state == CANCELLED:
                        raise ControllerAborted(f"program cancelled on the TNC after "
                                                f"{hits.made} of {total} touches")
                    raise LinkError(f"program finished with {hits.made} of {total} result "
                                    f"lines in {RESULTS}")
                now = time.monotonic()
                if state in (STOPPED, INTERRUPTED):
                    if now - held_t >= self.cfg.result_timeout_s:
                        raise LinkError(f"program {STATE_NAMES[state]} on the TNC for "
                                        f"{self.cfg.result_timeout_s:g} s ({hits.made} of "
                                        f"{total} touches)")
                else:
                    held_t = now
                if now - progress_t >= self.cfg.result_timeout_s:
                    raise LinkError(f"no result line for {self.cfg.result_timeout_s:g} s "
                                    f"(program {STATE_NAMES.get(state, state)}, {hits.made} "
                                    f"of {total} touches)")
                await asyncio.sleep(self.cfg.poll_interval_s)
        finally:
            self.say_step(None)

    @staticmethod
    def _decode(codec: DialectCodec, hits: HitFactory, line: str) -> ProbeHit | None:
        """One line of the result file: a touch (the next in program order, checked), None for
        other output (temperature lines)."""
        try:
            hit = codec.parse_result(line)
        except ValueError as e:
            raise LinkError(f"garbled line in {RESULTS}: {e}") from None
        if hit is None:
            return None
        if hit.seq != hits.made + 1:
            raise LinkError(f"{RESULTS}: result of touch seq {hits.made + 1} missing (next "
                            f"line: seq {hit.seq})")
        hit = hits.complete(hit, line)
        hits.made += 1
        return hit

    async def abort(self) -> None:
        """RUMBASTP.H with Q1689 = 1: the program ends (M30) at its next touch; a program not
        yet started ends at once when started. Waits until the TNC says it ended;
        ``LinkError`` for a program stopped there (NC stop) or not ending in time.

        pylsv2 replaces a file by deleting it, then writing it: a touch that calls the stop
        program in between finds none, and the TNC stops the program with an error ("file not
        found") — stopped all the same, with a message to acknowledge there."""
        if self._s.con is None:
            raise LinkError(f"{self._s.where}: not connected: the program was not stopped")
        self._stop_asked = True
        if await self._s.exists(self._path(PROGRAM)) is None:
            return  # no program of rumba's on the TNC: nothing to stop
        await self._s.put(self._path(STOP_PROGRAM), stop_program(True))
        deadline = time.monotonic() + self.cfg.stop_timeout_s
        while True:
            state = await self._s.program_state()
            if state not in (STARTED, STOPPED, INTERRUPTED):
                return
            if time.monotonic() > deadline:
                raise LinkError(f"the program did not end within {self.cfg.stop_timeout_s:g} s "
                                f"of the stop request (program {STATE_NAMES[state]}): stop it "
                                "at the machine (NC stop, internal stop)")
            await asyncio.sleep(self.cfg.poll_interval_s)
