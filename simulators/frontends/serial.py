"""Controller side of RS-232 DNC: a pty or TCP endpoint with a bounded, baud-paced receive buffer,
XON/XOFF, ``%`` framing, result lines (DPRNT/WRITE/F-PRINT) sent back and alarms on overflow;
the start-of-shift macro's request line ``RUMBA REQUEST <machine>`` on ``raise_start_request``.

Ptys and sockets deliver bytes instantly and enforce nothing, so the line is simulated here: bytes
enter the receive buffer no faster than the baud rate (bits per character from the framing), the
controller drains it one block at a time at its own execution pace, XOFF is sent at the high-water
mark and XON at the low-water mark; a byte the sender wrote after our XOFF could have reached it,
arriving into a full buffer, is an overflow alarm, as on a Fanuc (alarm SR0001-like "overrun").
drivers/README.md documents the serial settings.

This receive side is only as timely as its event loop, a real control's UART is not: while the
loop is late (the simulator's own computation, a loaded machine descheduling its process), the
sender keeps writing at the line rate into the pty or socket, and the XOFF goes out only once the
loop has caught up with that backlog. Bytes written before the XOFF went out are no protocol
violation, however many there are: they are told apart from later ones by counting what the
sender had written when the XOFF went out (``LineReader``), and those that do not fit wait on the
line until the control makes room (``line_holds``) instead of overflowing the buffer. Only what
the sender writes after the XOFF, beyond the slack above the high-water mark (the window it may
have in flight until it reads the XOFF), is the sender ignoring XOFF.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from simulators.frontends.lookahead import Lookahead
from simulators.frontends.serial_line import (  # noqa: F401 (SerialSettings: public here)
    FRAME_BITS,
    LineReader,
    SerialSettings,
)
from simulators.frontends.serial_ports import SerialEndpoints

XON, XOFF = 0x11, 0x13


class SerialFrontend(SerialEndpoints):
    """Serves one VirtualController over a pty (``open_pty``) and/or a TCP port (``open_tcp``).

    Statistics: ``alarms``, ``max_fill`` (highest buffer level), ``rx_bytes`` (through the
    line), ``xoff_sent``, ``line_holds`` (times bytes the sender wrote before our XOFF reached
    it waited on the line for room: this event loop had fallen behind the line)."""

    def __init__(self, controller: Any, settings: SerialSettings | None = None) -> None:
        self.ctrl = controller
        self.s = settings or SerialSettings()
        self.high, self.low = self.s.marks()
        self.alarms: list[str] = []  # every alarm reported on the line, in order
        self.max_fill = 0  # highest receive-buffer level seen (bytes)
        self.rx_bytes = 0
        self.xoff_sent = 0
        self.line_holds = 0
        self._buf = bytearray()
        self._have_line = asyncio.Event()
        # Set on every change a byte held on the line waits for: room in the buffer, the XOFF
        # state, more bytes from the sender (see _admit).
        self._wake = asyncio.Event()
        self._reader: LineReader | None = None
        self._rx_at_xoff = 0  # the sender's bytes received when our last XOFF went out
        self._xoff = False
        self._discard = False
        self._in_program = False
        self._t_line = 0.0
        self._writer: asyncio.StreamWriter | None = None
        self._out: asyncio.Queue[bytes] = asyncio.Queue()
        self._tasks: list[asyncio.Task] = []
        self._server: asyncio.base_events.Server | None = None
        self._fds: list[int] = []
        self._pipes: list[asyncio.BaseTransport] = []
        self._session_lock = asyncio.Lock()
        self._closing = False
        self._garble_lines = 0
        self._self_reset = False
        # Tape framing: the control's RESET count when the reader took the current tape's
        # leader, and how many blocks of that tape it has handed on (see _block).
        self._leader_resets = 0
        self._tape_blocks = 0
        self._last_state = "idle"
        self._unplugged_until = 0.0
        self._tcp_writer: asyncio.StreamWriter | None = None
        self._look = Lookahead(controller, self.s.lookahead_blocks)
        self._tasks.append(asyncio.create_task(self._events()))

    # ------------------------------------------------------------------ one connection

    async def _session(self, reader: LineReader, writer: asyncio.StreamWriter) -> None:
        async with self._session_lock:
            self._writer = writer
            self._reader = reader
            self._buf.clear()
            self._xoff = self._discard = False
            consumer = asyncio.create_task(self._consume())
            sender = asyncio.create_task(self._send())
            try:
                await self._receive(reader)
                # EOF: what already crossed the line is still executed (bounded wait).
                unplugged = time.monotonic() < self._unplugged_until
                for _ in range(0 if unplugged else 200):
                    if b"\n" not in self._buf or self._discard or consumer.done():
                        break
                    await asyncio.sleep(0.01)
            finally:
                consumer.cancel()
                sender.cancel()
                await asyncio.wait({consumer, sender}, timeout=2.0)
                if self._in_program and not self._discard and not self._closing:
                    await self._alarm("DNC stream interrupted (line closed mid-program)")
                self._in_program = False
                writer.close()
                self._writer = None
                self._reader = None

    async def _receive(self, reader: asyncio.StreamReader) -> None:
        cps = self.s.chars_per_s
        while True:
            try:
                data = await reader.read(1024)
            except (ConnectionError, OSError):
                return
            if not data:
                return
            for i in range(0, len(data), 8):
                piece = data[i:i + 8]
                # The line carries one character per 1/cps s; a sender writing faster only
                # fills the OS buffer, it does not reach the controller sooner.
                # Scheduling jitter (the control's own computation shares this event loop)
                # may make us late; catching up by up to 64 character times keeps the average
                # at the line rate without lagging behind a sender that paces itself.
                now = time.monotonic()
                self._t_line = max(self._t_line, now - 64 / cps) + len(piece) / cps
                if self._t_line > now:
                    await asyncio.sleep(self._t_line - now)
                self.rx_bytes += len(piece)
                if time.monotonic() < self._unplugged_until:
                    continue  # cable pulled: the bytes are lost
                if self.s.disconnect_after_bytes and self.rx_bytes >= self.s.disconnect_after_bytes:
                    return
                await self._admit(piece)

    async def _admit(self, piece: bytes) -> None:
        if self._discard:
            return
        if self.s.framing.startswith("7") and any(b > 0x7F for b in piece):
            await self._alarm("parity error on the serial line (8-bit byte on a 7E1 port)")
            return
        held = False
        while len(self._buf) + len(piece) > self.s.rx_buffer_bytes:
            overflow = f"serial receive buffer overflow ({self.s.rx_buffer_bytes} bytes)"
            if not self._xoff:
                # No XOFF to ignore: the control asked for the rest of a block longer than
                # the buffer (_consume), or the high-water mark is the buffer size.
                await self._alarm(overflow)
                return
            if self._written_after_xoff() > self.s.rx_buffer_bytes - self.high:
                await self._alarm(f"{overflow}: the sender ignored XOFF")
                return
            # Written before our XOFF could reach the sender: on a real line these bytes came
            # in while the XOFF went out in time; here this loop was late. They wait on the line
            # (in the pty or socket) until the control makes room; a sender that goes on writing
            # is caught above as soon as its bytes after the XOFF exceed the slack.
            if not held:
                held = True
                self.line_holds += 1
            self._wake.clear()
            await self._wake.wait()
            if self._discard:
                return
        self._buf.extend(piece)
        self.max_fill = max(self.max_fill, len(self._buf))
        if b"\n" in piece:
            self._have_line.set()
        if len(self._buf) >= self.high and not self._xoff:
            self._xoff = True
            self.xoff_sent += 1
            self._put_flow(XOFF)
            self._mark_xoff()

    def _mark_xoff(self) -> None:
        """Count what the sender had written when our XOFF went out: everything the OS holds
        for us now is from before (it cannot have read the XOFF yet), whatever this loop had
        not read so far; only bytes written later count against it."""
        if self._reader is not None:
            self._reader.drain()
            self._rx_at_xoff = self._reader.received

    def _written_after_xoff(self) -> int:
        """Bytes the sender wrote after our XOFF went out (give or take those it wrote while
        the XOFF was going out: ``_mark_xoff`` reads the OS just after sending it)."""
        if self._writer is not None and self._writer.transport.get_write_buffer_size() > 0:
            self._mark_xoff()  # the XOFF may still wait in our output buffer: not sent yet
        return self._reader.received - self._rx_at_xoff if self._reader is not None else 0

    def _put_flow(self, byte: int) -> None:
        # Flow-control characters go out at once, ahead of any queued result line.
        if self._writer is not None and not self._writer.is_closing():
            self._writer.write(bytes([byte]))

    def _spawn(self, coro: Any) -> None:
        task = asyncio.create_task(coro)
        self._tasks.append(task)
        task.add_done_callback(lambda t: t in self._tasks and self._tasks.remove(t))

    async def _xon_later(self) -> None:
        if self.s.xon_missing:
            return
        if self.s.xon_delay_s:
            await asyncio.sleep(self.s.xon_delay_s)
        # Only if no XOFF was sent since this XON was decided: bytes held on the line, woken by
        # the room that decided it, can refill the buffer past the high mark first, and an XON
        # sent after that XOFF freed the sender while we counted its bytes as written after
        # XOFF ("the sender ignored XOFF" under load).
        if not self._xoff:
            self._put_flow(XON)

    async def _consume(self) -> None:
        while True:
            nl = self._buf.find(b"\n")
            if nl < 0:
                if self._xoff:
                    # A block longer than the low-water mark is half in: ask for the rest,
                    # or sender and control would wait for each other forever.
                    self._xoff = False
                    self._spawn(self._xon_later())
                    self._wake.set()
                self._have_line.clear()
                await self._have_line.wait()
                continue
            raw = bytes(self._buf[:nl + 1])
            del self._buf[:nl + 1]
            self._wake.set()  # room for bytes held on the line
            if self._xoff and len(self._buf) <= self.low:
                self._xoff = False
                self._spawn(self._xon_later())
            line = raw.decode("ascii", "replace").strip("\r\n").replace(chr(XON), "").replace(
                chr(XOFF), "")
            await self._block(line)

    def _reset_since_leader(self) -> bool:
        return getattr(self.ctrl, "resets", 0) != self._leader_resets

    async def _block(self, line: str) -> None:
        """The tape reader: a program is ``%`` … ``%``. After a RESET the control drops the
        rest of the tape it was reading and waits for the next leading ``%``; a ``%`` with no
        block since the last one is an empty record, not a program, so it leads the next tape
        (the closing ``%`` of a tape cut after a RESET, then the next tape's own, are read as
        one leader: never as an empty program that would take the next tape's leader as its
        end). Both are decided here, in the order the bytes came, never by the controller's
        events, which arrive later (a block read meanwhile would start a new program)."""
        stripped = line.strip()
        if self._in_program and not self._discard and self._reset_since_leader():
            self._in_program = False  # RESET at the control: the rest of this tape is dropped
        if stripped.startswith("%"):
            if not self._in_program or not self._tape_blocks:
                if self.ctrl.state in ("running", "hold"):
                    # The next tape (a verdict program after the probing one) is read when
                    # the running program has ended, as at the control's next cycle start.
                    await self.ctrl.wait_done()
                self._in_program, self._discard = True, False
                self._leader_resets, self._tape_blocks = getattr(self.ctrl, "resets", 0), 0
                self._look.reset()
            else:
                self._in_program = False
                await self.ctrl.end_of_stream()
            return
        if not self._in_program or self._discard or not stripped:
            return  # leader before the first '%' is skipped, as a tape reader does
        if await self._look.feed(stripped, still=lambda: not self._reset_since_leader()):
            self._tape_blocks += 1
        else:  # RESET while the block waited for the look-ahead: this tape is dropped
            self._in_program = False

    # ------------------------------------------------------------------ controller → line

    async def _alarm(self, text: str) -> None:
        if self._discard:
            return
        self._discard = True
        self._buf.clear()
        self._wake.set()
        self.alarms.append(text)
        raise_alarm = getattr(self.ctrl, "raise_alarm", None)
        if callable(raise_alarm):
            raise_alarm(text)
        else:
            self._self_reset = self._in_program
            await self.ctrl.abort()
            # Our own reset: this tape is discarded to its end (``%``), not dropped at once.
            self._leader_resets = getattr(self.ctrl, "resets", 0)
        self._line(f"ALARM: {text}")

    def _fault(self, fault: Any) -> None:
        """Transport faults of the controller's fault plan (simulators/faults.py)."""
        if fault.kind == "late_xon":
            self.s.xon_delay_s = fault.duration_s or 2.0
        elif fault.kind == "missing_xon":
            self.s.xon_missing = True
        elif fault.kind == "garbled":
            self._garble_lines += fault.count
        elif fault.kind == "disconnect":
            self._unplugged_until = time.monotonic() + (fault.duration_s or 1e9)
            if self._tcp_writer is not None:
                self._tcp_writer.transport.abort()  # TCP: the connection drops at once

    def _garble(self, text: str) -> str:
        self._garble_lines -= 1
        # Line noise after the first word: every third character replaced, as a bad cable does.
        return text[:6] + "".join("~" if i % 3 == 1 else ch for i, ch in enumerate(text[6:]))

    def _line(self, text: str) -> None:
        if time.monotonic() < self._unplugged_until:
            return
        eol = "\r\n" if self.s.eol == "CRLF" else "\n"
        self._out.put_nowait((text + eol).encode("ascii", "replace"))

    async def _events(self) -> None:
        async for ev in self._look.events():
            kind = type(ev).__name__
            was = self._last_state
            if kind == "StateChange":
                self._last_state = ev.state
            if kind == "PrintLine":
                self._line(self._garble(ev.text) if self._garble_lines else ev.text)
            elif kind == "RequestRaised":
                # The start-of-shift macro's print command (DPRNT / WRITE / FN 16 / PRINT).
                self._line(f"RUMBA REQUEST {ev.machine}")
            elif kind == "FaultEvent":
                self._fault(ev.fault)
            elif kind == "StateChange" and ev.state == "alarm":
                # The control stopped: what is still on the line is not executed.
                self._discard = self._in_program
                self._buf.clear()
                self._wake.set()
                if ev.alarm and ev.alarm not in self.alarms:
                    self.alarms.append(ev.alarm)
                    self._line(f"ALARM: {ev.alarm}")
            elif (kind == "StateChange" and ev.state == "idle" and self._in_program
                  and was in ("running", "hold", "alarm")):
                if self._self_reset:  # our own overflow alarm: keep discarding this tape
                    self._self_reset = False
                elif self._reset_since_leader():  # not yet seen by _block (a later tape's is)
                    # RESET at the control: the rest of the tape is dropped, the reader waits
                    # for the leader of a new one.
                    self._discard = self._in_program = False
                    self._buf.clear()
                    self._wake.set()

    async def _send(self) -> None:
        cps = self.s.chars_per_s
        t = time.monotonic()
        while True:
            data = await self._out.get()
            if self._writer is None:
                continue
            for i in range(0, len(data), 16):
                piece = data[i:i + 16]
                t = max(t, time.monotonic()) + len(piece) / cps
                self._writer.write(piece)
                delay = t - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
