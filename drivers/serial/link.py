"""RS-232 DNC drip-feed link: streams a ``%``-framed program with XON/XOFF honoured and captures
the result lines (DPRNT / WRITE / F-PRINT) the program prints back on the same port; takes the
start-of-shift request line ``RUMBA REQUEST <machine>`` the CNC's macro prints, and writes the
verdict back by drip-feeding the dialect's three-block verdict program.

Opened with pyserial's ``serial_for_url`` (device path, ``socket://host:port``, ``rfc2217://``).
Flow control is done here, not by the OS: ptys and sockets ignore XON/XOFF and a kernel tty would
swallow them, so the sender writes at most ``tx_chunk_bytes`` ahead at the baud rate and stops on
XOFF (0x13) until XON (0x11). Settings are documented in drivers/README.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import termios
import time
from collections.abc import AsyncIterator, Callable

import serial

from contracts.jobs import DialectCodec, ProgramJob, Verdict
from contracts.messages import ProbeHit
from drivers.base import Capabilities, CncLink, ControllerAlarm, LinkError, StartRequest
from drivers.hits import HitFactory
from drivers.retry import wait_event
from drivers.serial.leftover import drain_leftover
from drivers.serial.lines import (  # noqa: F401 (re-exported: the link's public names)
    MAX_LINE_BYTES,
    REQUEST_HOLDOFF_S,
    XOFF,
    XON,
    PrintedTemperatures,
    _DncProtocol,
    cut_point,
    parse_request,
)
from drivers.serial.schema import SerialLinkConfig
from drivers.serial.transport import ThreadTransport, create_serial_connection

log = logging.getLogger("rumba.serial")

MAX_WRITE_BYTES = 32
"""At most this much per write and per pass through the event loop's timers (a UART's transmit
FIFO is 16-64 bytes): a peer reading the line on its own ≈ 1 ms timer (the pty simulator's
paced receive) is never handed more per tick than it takes; 32 per ms is still ≥ 115 200 baud."""

FRAME = {"7E1": (7, "E", 1, 10), "8N1": (8, "N", 1, 10), "7E2": (7, "E", 2, 11),
         "8N2": (8, "N", 2, 11)}
"""framing → (data bits, parity, stop bits, bits per character on the line)."""

ResultParser = Callable[[str], "ProbeHit | None"]


def _is_pty(url: str) -> bool:
    """A device path that is a Unix98 pseudo-terminal (the simulator, socat)."""
    if "://" in url:
        return False
    try:
        return os.path.realpath(url).startswith("/dev/pts/")
    except OSError:
        return False


def frame_program(text: str, eol: str, seven_bit: bool) -> bytes:
    """``%`` leader and trailer, one block per line with the configured end of block."""
    lines = [ln.rstrip("\r") for ln in text.replace("\r\n", "\n").split("\n")]
    for n, ln in enumerate(lines, 1):
        bad = [c for c in ln if ord(c) > (0x7F if seven_bit else 0xFF) or c in "\x11\x13"]
        if bad:
            raise LinkError(f"program line {n} contains {bad[0]!r}, which the serial line "
                            "cannot carry (7-bit ASCII, no XON/XOFF characters)")
    lines = [ln for ln in lines if ln.strip()]
    if not lines or lines[0].strip() != "%":
        lines.insert(0, "%")
    if len(lines) < 2 or lines[-1].strip() != "%":
        lines.append("%")
    sep = "\r\n" if eol == "CRLF" else "\n"
    return (sep.join(lines) + sep).encode("latin-1")


class SerialDncLink(PrintedTemperatures, CncLink):
    """DNC drip-feed over RS-232 (or a serial server reached by ``socket://`` / ``rfc2217://``)."""

    capabilities = Capabilities(start_request=True, streams_blocks=True, loads_program=False,
                                writes_verdict=True, can_abort=True)
    uses_dialect = True  # the verdict goes back as a small program in the machine's dialect

    def __init__(self, cfg: SerialLinkConfig, parse_result: ResultParser | None = None,
                 dialect: DialectCodec | None = None) -> None:
        self.cfg = cfg
        self._parse = parse_result
        self.dialect = dialect  # for the verdict program; the last job's codec otherwise
        self._tape_open = False  # a stream was cut short: the control is inside a program
        self._stale = False  # an aborted program's last results may still arrive
        self._fed = b""  # the last tape as far as it was fed (a stopped one: up to its cut)
        self._drain: asyncio.Task | None = None  # a stopped program's output being read
        self._cut = asyncio.Event()  # stop the stream at the end of the current block
        self._tx_lock = asyncio.Lock()
        self._proto: _DncProtocol | None = None
        self._transport: asyncio.BaseTransport | ThreadTransport | None = None
        self._sender: asyncio.Task | None = None
        self.bytes_sent = 0
        self.stream_s = 0.0  # wall time of the last stream (throughput = bytes_sent / stream_s)
        self._holdoff_until = 0.0  # survives a reconnect: see REQUEST_HOLDOFF_S
        # A real UART's output queue is read with TIOCOUTQ; ptys and sockets have none.
        self._real_tty = "://" not in cfg.url and not _is_pty(cfg.url)

    @property
    def chars_per_s(self) -> float:
        return self.cfg.baudrate / FRAME[self.cfg.framing][3]

    async def connect(self) -> None:
        if self._transport is not None:
            return
        bits, parity, stop, _ = FRAME[self.cfg.framing]
        if _is_pty(self.cfg.url):
            # A pseudo-terminal has no UART (Linux refuses 7-bit/parity settings on it): open
            # it 8N1; 7-bit framing is still enforced on the program text and paced here.
            bits, parity, stop = 8, "N", 1
        kw = dict(baudrate=self.cfg.baudrate, bytesize=bits, parity=parity, stopbits=stop,
                  xonxoff=False, rtscts=False)
        proto = _DncProtocol(self.cfg.request_machine, self._holdoff_until)
        loop = asyncio.get_running_loop()
        try:
            if self.cfg.url.startswith("rfc2217://"):
                ser = await asyncio.wait_for(loop.run_in_executor(
                    None, lambda: serial.serial_for_url(self.cfg.url, timeout=0.1, **kw)),
                    self.cfg.connect_timeout_s)
                self._transport = ThreadTransport(ser, proto, loop)
            else:
                self._transport, _ = await asyncio.wait_for(
                    create_serial_connection(loop, lambda: proto, self.cfg.url, **kw),
                    self.cfg.connect_timeout_s)
        except (TimeoutError, serial.SerialException, OSError, ValueError, termios.error) as e:
            raise LinkError(f"serial {self.cfg.url}: cannot open: "
                            f"{str(e) or 'timeout'}") from None
        self._proto = proto

    async def wait_start_request(self) -> StartRequest:
        """The next ``RUMBA REQUEST <machine>`` line printed by the CNC's start-of-shift macro
        (with ``request_machine`` set, requests naming another machine are logged, ignored).
        Calling it again ends the service of the previous request: repeats are refused until
        then and for ``request_holdoff_s`` after that run's end."""
        if self._proto is None:
            raise LinkError("serial link not connected")
        proto = self._proto
        proto.serving = False
        item = await proto.requests.get()
        if isinstance(item, BaseException):
            raise LinkError(str(item))
        machine, line = item
        proto.serving = True
        return StartRequest(source="cnc", machine=machine, detail=f"serial line: {line}")

    def _run_ended(self) -> None:
        self._holdoff_until = time.monotonic() + self.cfg.request_holdoff_s
        if self._proto is not None:
            self._proto.holdoff_until = self._holdoff_until

    async def _stream(self, payload: bytes, measure: bool = True) -> None:
        async with self._tx_lock:
            self._tape_open = True
            self._cut.clear()
            await self._paced(payload, measure)
            self._tape_open = False

    async def _end_tape(self, sender: asyncio.Task | None) -> None:
        """Stop feeding at the end of the block being sent and close the tape (``%``): a
        block cut in the middle would be executed truncated (``X12`` for ``X123.456``).

        The cut is a few bytes, paced and flow-controlled like any others: it ends, or the
        sender fails on its own (XOFF held past ``xoff_timeout_s``: the control has to be reset
        there, the tape stays open). Never cancelled on a clock: a cut given up after 5 s under
        load left half a block on the tape, and the next tape's leader was read as the rest of
        it (``N336 G01 X-166.7855 Y%``, an alarm at the control). A caller that stops waiting
        (a bounded abort) leaves it running; the next tape waits for it (``_tx_lock``)."""
        if sender is None or sender.done():
            return
        self._cut.set()
        with contextlib.suppress(Exception):  # its failure is the open tape (_tape_open)
            await asyncio.shield(sender)

    async def _paced(self, payload: bytes, measure: bool) -> None:
        """Feed ``payload`` as a UART would, never more than ``tx_chunk_bytes`` in flight.

        In flight = written but, at the line rate, not yet through the line: everything in
        flight still reaches the control after it sends XOFF, so it must fit the control's
        slack above its high-water mark (``tx_chunk_bytes`` is set to at most that). The line
        clock ``line_t`` is when the last byte written leaves the line; like a UART it never
        runs ahead of real time after a stall (no catch-up burst: a line idle during a stall
        carried nothing, so what the line did not carry then is still in flight later). Each
        write is what fits in the budget at that moment."""
        assert self._proto is not None and self._transport is not None
        proto, transport = self._proto, self._transport
        self._fed = b""
        cps, budget = self.chars_per_s, self.cfg.tx_chunk_bytes
        t0 = line_t = time.monotonic()
        i, cut = 0, False
        while i < len(payload):
            if self._cut.is_set() and not cut:
                if not i:
                    return  # nothing of this tape reached the control
                # the control is inside the tape: the rest of its block, then the tape's end,
                # fed like any other bytes (paced, and never while the control holds XOFF: a
                # cut written at once overran a full receive buffer)
                rest = payload[i:cut_point(payload, i)]
                payload = (payload[:i] + rest + (b"" if rest.endswith(b"\n") else b"\n") + b"%"
                           + (b"\r\n" if self.cfg.eol == "CRLF" else b"\n"))
                self._stale = True  # results of the blocks it holds may still arrive
                cut = True
                continue
            if self.cfg.xonxoff and not proto.xon.is_set():
                if not await wait_event(proto.xon, self.cfg.xoff_timeout_s):
                    raise LinkError(f"controller held XOFF for {self.cfg.xoff_timeout_s:g} s "
                                    f"(no XON) after {i} of {len(payload)} bytes")
                continue
            now = time.monotonic()
            ahead = max(line_t - now, 0.0) * cps + self._os_pending()
            room = int(budget - ahead)
            if room >= 1:
                piece = payload[i:i + min(room, MAX_WRITE_BYTES)]
                transport.write(piece)  # type: ignore[union-attr]
                self._fed = payload[:i + len(piece)]
                # The clock read after the write: the line starts on these bytes no earlier.
                line_t = max(line_t, time.monotonic()) + len(piece) / cps
                i += len(piece)
                if measure:
                    self.bytes_sent += len(piece)
                ahead += len(piece)
            # One write per pass through the loop's timers, then sleep until a byte fits (the
            # timer granularity, ≈ 1 ms with epoll, makes it longer; on waking whatever fits
            # by then goes out). An XOFF arriving meanwhile is read before we wake (I/O
            # callbacks run before timers); one sent in the same pass is not, which the
            # budget covers.
            await asyncio.sleep(max((ahead + 1 - budget) / cps, 1e-6))
        if measure:
            self.stream_s = time.monotonic() - t0

    def _os_pending(self) -> int:
        """Bytes the transport or the OS still holds unsent (a real UART's output queue; 0 for
        a pty or socket, which hand bytes on at once)."""
        t = self._transport
        pending = 0
        if t is not None and hasattr(t, "get_write_buffer_size"):
            pending = t.get_write_buffer_size()
        ser = getattr(t, "serial", None) if self._real_tty else None
        if ser is not None:
            try:
                pending += ser.out_waiting
            except (OSError, serial.SerialException, AttributeError, NotImplementedError):
                self._real_tty = False  # no TIOCOUTQ here: the line clock alone
        return pending

    async def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        if self._proto is None:
            raise LinkError("serial link not connected")
        codec = job.codec or self.dialect
        if self._parse is None and codec is None:
            raise LinkError(f"no result decoder for the {job.dialect} program (the job carries "
                            f"no dialect codec)")
        parse = self._parse or codec.parse_result  # type: ignore[union-attr]
        payload = frame_program(job.text, self.cfg.eol, self.cfg.framing.startswith("7"))
        proto, hits = self._proto, HitFactory(job)
        if job.codec is not None:
            self.dialect = job.codec
        if self._drain is not None:  # the stopped program's last lines first (bounded)
            self._stale = not await self._drain
            self._drain = None
            proto.temperatures.clear()  # its RTEMP lines are not this run's readings
        while not proto.lines.empty():  # stale output from before this run
            item = proto.lines.get_nowait()
            if isinstance(item, BaseException):
                raise LinkError(str(item))
        if self._tape_open:
            log.warning("serial: the previous program was cut short; the control must have "
                        "been reset since (plain DNC has no remote reset)")
        self.bytes_sent = 0
        proto.running = True
        self._sender = sender = asyncio.create_task(self._stream(payload))
        got: set[int] = set()
        alarmed = False
        try:
            while True:
                if sender.done() and sender.exception() is not None:
                    raise sender.exception()  # type: ignore[misc]
                if sender.done() and len(got) >= job.touch_count:
                    return
                getter = asyncio.ensure_future(proto.lines.get())
                wait = {getter} if sender.done() else {getter, sender}
                done, _ = await asyncio.wait(
                    wait, timeout=self.cfg.result_timeout_s if sender.done() else None,
                    return_when=asyncio.FIRST_COMPLETED)
                if getter not in done:
                    getter.cancel()
                    if sender in done:
                        continue
                    raise LinkError(f"no result line for {self.cfg.result_timeout_s:g} s after "
                                    f"the program ended ({len(got)} of {job.touch_count} touches)")
                item = getter.result()
                if isinstance(item, BaseException):
                    raise item
                if item.upper().startswith("ALARM"):
                    alarmed = True
                    raise ControllerAlarm(f"controller: {item}")
                try:
                    hit = parse(item)
                except ValueError as e:  # a RUMBA line broken in transit: a hit would be lost
                    raise LinkError(f"garbled result line from the controller: {e}") from None
                if hit is None:
                    continue  # other program output (messages, echo of comments)
                if self._stale and not got and hit.seq != 1:
                    log.info("serial: result of the aborted program dropped: %s", item)
                    continue
                self._stale = False
                hit = hits.complete(hit, item)
                if hit.seq != len(got) + 1 and hit.seq not in got:
                    # A result line went missing (noise, a dropped line): never guess it.
                    raise LinkError(f"result line of touch seq {len(got) + 1} lost "
                                    f"(next line received: seq {hit.seq})")
                got.add(hit.seq)
                yield hit
                if not hit.triggered:
                    alarmed = True
                    raise ControllerAlarm(f"probe did not trigger at touch seq {hit.seq}")
        finally:
            self._run_ended()
            await self._end_tape(sender)
            if alarmed:
                # A control in alarm has dropped the rest of the tape itself.
                self._tape_open = False
            last = (0 if alarmed or self._tape_open or codec is None
                    else getattr(codec, "last_printed_seq", lambda _: 0)(
                        self._fed.decode("latin-1")))
            if last > max(got, default=0):
                # Stopped early, the control runs on through what it holds: its lines are
                # read (running) until the last of them came, before the next tape goes.
                self._drain = asyncio.ensure_future(drain_leftover(
                    proto.lines, parse, max(got, default=0), last,
                    self.cfg.result_timeout_s))
                self._drain.add_done_callback(lambda _t: setattr(proto, "running", False))
            else:
                proto.running = False

    async def write_verdict(self, verdict: Verdict) -> None:
        """Drip-feed the dialect's verdict program (programs/dialects ``verdict_program``):
        it sets the verdict variable the start-of-shift macro waits for (#598, R4, Q1598,
        #3998). Only the integer code reaches the program text."""
        if self._proto is None or self._transport is None:
            raise LinkError("serial link not connected")
        if self.dialect is None:
            raise LinkError("no dialect known for the verdict program (serial link created "
                            "without dialect= and no program run yet)")
        await self._end_tape(self._sender)  # a stopped program's cut ends first
        try:
            text = self.dialect.verdict_program(verdict.code)
        except ValueError as e:  # the dialect refuses anything but a verdict code
            raise LinkError(str(e)) from None
        if self._tape_open:
            # The control still sits inside the program we stopped feeding: what we send now
            # would be read as its next blocks. Its verdict variable stays 0 (the macro
            # cleared it), so production is not released.
            raise LinkError(f"verdict {verdict.status} not written: the control is still "
                            "inside the interrupted program (plain DNC has no remote reset); "
                            "reset the control")
        payload = frame_program(text, self.cfg.eol, self.cfg.framing.startswith("7"))
        try:
            await self._stream(payload, measure=False)
        finally:
            self._run_ended()

    async def abort(self) -> None:
        """Plain DNC has no remote reset: stop feeding, then close the tape with its end of
        record (``%``), so the control ends the program after the blocks it already holds and
        reads the next tape as a new program (an open tape would take the next program's
        leader as its end, and its blocks as garbage)."""
        await self._end_tape(self._sender)

    async def close(self) -> None:
        if self._drain is not None:
            self._drain.cancel()
            self._drain = None
        await self.abort()
        if self._transport is not None:
            self._transport.close()
            self._transport = None
            self._proto = None
