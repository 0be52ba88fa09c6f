"""Receive side of the serial DNC link: lines from the control, XON/XOFF state, and the
start-of-shift request (a level, at most one pending, with a hold-off after each run)."""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections import deque

from contracts.temperatures import parse_printed
from drivers.base import LinkError

log = logging.getLogger("rumba.serial")

XON, XOFF = 0x11, 0x13

MAX_LINE_BYTES = 1024
"""Longest line accepted from the control (result lines are < 120 characters): a longer run of
bytes without a newline is noise or a wrong baud rate, not a line; it is discarded, so the
receive buffer never grows past this."""

REQUEST_HOLDOFF_S = 5.0
"""Start-request repeats within this time after a run's end (its verdict fed or the run
stopped) are refused: the macro's repeated request lines still on the line are echoes of the
request just served, not a new start-of-shift. The default of ``request_holdoff_s`` in the
link's configuration."""

# The start-of-shift macro's request line (gcode_templates/*/README.md; the dialect's macro
# clears the verdict variable, prints this line, waits for the verdict).
_REQUEST = re.compile(r"^\s*RUMBA\s+REQUEST\s+(?P<machine>[A-Za-z0-9_.-]{1,32})\s*$", re.ASCII)
_REQUEST_HEAD = re.compile(r"^\s*RUMBA\s+REQUEST\b", re.IGNORECASE)


def parse_request(line: str) -> str | None:
    """The machine named by a start-of-shift request line ``RUMBA REQUEST <machine>`` (printed
    by the CNC's start-of-shift macro), None for any other line; ``ValueError`` for a line that
    starts like a request but breaks the grammar (a request is never guessed)."""
    if not _REQUEST_HEAD.match(line):  # a prefix test: match is meant
        return None
    m = _REQUEST.fullmatch(line.rstrip("\r\n"))
    if not m:
        raise ValueError(f"request line does not match 'RUMBA REQUEST <machine>' with machine "
                         f"[A-Za-z0-9_.-]{{1,32}}: {line.strip()[:80]!r}")
    return m.group("machine")


class _DncProtocol(asyncio.Protocol):
    """Splits received bytes into lines and tracks the controller's XON/XOFF state.

    A start request is a level, not a queue: at most one is pending (``requests`` holds 0 or
    1); a request line while one is pending or being served (``serving``: handed out, its run
    and verdict not yet over), while a program runs, or within ``REQUEST_HOLDOFF_S`` after a
    run's end is refused and logged, never queued for later. Other lines go to ``lines``
    while a program runs and are otherwise logged and kept in ``unsolicited`` (the last 100),
    never mistaken for results."""

    def __init__(self, request_machine: str | None = None, holdoff_until: float = 0.0) -> None:
        self.lines: asyncio.Queue[str | BaseException] = asyncio.Queue()
        self.requests: asyncio.Queue[tuple[str, str] | BaseException] = asyncio.Queue()
        self.unsolicited: deque[str] = deque(maxlen=100)
        self.request_machine = request_machine
        self.running = False
        self.serving = False
        self.holdoff_until = holdoff_until  # time.monotonic() before which requests are refused
        self.requests_seen = 0
        self.requests_refused = 0
        self.xon = asyncio.Event()
        self.xon.set()
        self.xoff_count = 0
        self._partial = bytearray()
        self._overlong = False  # discarding the rest of an over-long line up to its newline
        self.overlong_lines = 0
        self.transport: asyncio.BaseTransport | None = None
        self.temperatures: list[str] = []  # RTEMP lines of the running program

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        if XON in data or XOFF in data:
            for b in data:
                if b == XOFF:
                    self.xon.clear()
                    self.xoff_count += 1
                elif b == XON:
                    self.xon.set()
            data = data.replace(bytes([XON]), b"").replace(bytes([XOFF]), b"")
        start = 0
        while (nl := data.find(b"\n", start)) >= 0:
            self._take(data[start:nl])
            if not self._overlong:
                raw = bytes(self._partial)
                line = raw.decode("ascii", "replace").strip("\r").strip()
                if line:
                    self._dispatch(line)
            self._partial.clear()
            self._overlong = False
            start = nl + 1
        self._take(data[start:])

    def _take(self, piece: bytes) -> None:
        """Append to the current line, up to ``MAX_LINE_BYTES``; the rest of a longer line is
        dropped as it arrives (the buffer stays bounded whatever the line sends)."""
        if self._overlong or not piece:
            return
        if len(self._partial) + len(piece) <= MAX_LINE_BYTES:
            self._partial += piece
            return
        head = bytes(self._partial[:80]).decode("ascii", "replace")
        self._partial.clear()
        self._overlong = True
        self.overlong_lines += 1
        msg = (f"line from the controller longer than {MAX_LINE_BYTES} bytes without a "
               f"newline (starts {head!r}): discarded; wrong baud rate/framing or line noise")
        log.error("serial: %s", msg)
        self.unsolicited.append(f"<discarded over-long line starting {head!r}>")
        if self.running:
            # A result line may be inside it: the run cannot complete, end it now with the
            # reason rather than after result_timeout_s.
            self.lines.put_nowait(LinkError(msg))

    def _refuse(self, line: str, why: str) -> None:
        self.requests_refused += 1
        log.warning("serial: start request %r refused: %s", line, why)
        self.unsolicited.append(line)

    def _dispatch(self, line: str) -> None:
        try:
            machine = parse_request(line)
        except ValueError as e:
            log.warning("serial: %s; ignored", e)
            self.unsolicited.append(line)
            return
        if machine is not None:
            self.requests_seen += 1
            want = self.request_machine
            if want is not None and machine.upper() != want.upper():
                log.warning("serial: start request for machine %s ignored (this line serves "
                            "%s)", machine, want)
                self.unsolicited.append(line)
            elif self.running:
                self._refuse(line, "a program is running")
            elif self.serving:
                self._refuse(line, "the previous request is still being served")
            elif not self.requests.empty():
                self._refuse(line, "a request is already pending (a request is a level)")
            elif time.monotonic() < self.holdoff_until:
                self._refuse(line, "too soon after the last run's end (hold-off)")
            else:
                self.requests.put_nowait((machine, line))
        elif self.running and line.startswith("RTEMP"):
            self.temperatures.append(line)  # a temperature, never a result (PrintedTemperatures)
        elif self.running:
            self.lines.put_nowait(line)
        else:
            log.info("serial: line outside a run ignored: %r", line[:120])
            self.unsolicited.append(line)

    def connection_lost(self, exc: Exception | None) -> None:
        err = LinkError(f"serial line closed{f': {exc}' if exc else ''}")
        self.lines.put_nowait(err)
        self.requests.put_nowait(err)
        self.xon.set()


class PrintedTemperatures:
    """The DNC link's temperatures: the ``RTEMP`` lines its program printed."""

    _proto: _DncProtocol | None

    def printed_temperatures(self) -> list[tuple[int, str, float]]:
        proto = self._proto
        if proto is None:
            return []
        lines, proto.temperatures = proto.temperatures, []
        out = []
        for line in lines:
            try:
                out.append(parse_printed(line))
            except ValueError as e:  # a reading garbled in transit: lost, said, never guessed
                log.warning("serial: %s; reading dropped", e)
        return out


_OPENS = re.compile(rb"^\s*(?:N\d+\s+)?(?:IF\b(?!.*\bGOTO)|o\d+\s+if\b)", re.I)
_CLOSES = re.compile(rb"^\s*(?:N\d+\s+)?(?:ENDIF\b|o\d+\s+endif\b)", re.I)


def cut_point(payload: bytes, i: int) -> int:
    """Where a stream stopped at byte ``i`` may end: after the line being sent, and after every
    multi-line IF it opened is closed (Siemens ``IF … ENDIF``, LinuxCNC ``o… if/endif``): a tape
    cut inside one is a syntax alarm at the control, not a stop (single-line Fanuc ``IF […]
    GOTO`` and Heidenhain ``FN 9`` need no close)."""
    depth, start = 0, 0
    while True:
        end = payload.find(b"\n", start)
        line = payload[start:] if end < 0 else payload[start:end]
        if _OPENS.match(line):
            depth += 1
        elif _CLOSES.match(line) and depth:
            depth -= 1
        if end < 0:
            return len(payload)
        start = end + 1
        if start > i and depth == 0:
            return start
