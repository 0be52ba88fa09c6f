"""The simulated serial line's settings and receive side (simulators/frontends/serial.py): the
framing and buffer levels of ``SerialSettings``, and ``LineReader``, a stream that counts what the
sender delivered and can take at once what the OS holds, however late the event loop is."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

FRAME_BITS = {"7E1": 10, "8N1": 10, "7E2": 11, "8N2": 11}
"""Bits on the line per character: start + data + parity + stop."""


@dataclass
class SerialSettings:
    baudrate: int = 9600
    framing: Literal["7E1", "8N1", "7E2", "8N2"] = "7E1"
    eol: Literal["LF", "CRLF"] = "CRLF"  # end of line of what the controller sends back
    rx_buffer_bytes: int = 256
    high_water: int | None = None  # default: half the buffer (room for what is in flight)
    low_water: int | None = None  # default: buffer / 4
    xon_delay_s: float = 0.0  # fault: late XON
    xon_missing: bool = False  # fault: XON never sent
    disconnect_after_bytes: int | None = None  # fault: drop the line mid-stream
    lookahead_blocks: int = 8  # blocks the control takes ahead of execution

    @property
    def chars_per_s(self) -> float:
        return self.baudrate / FRAME_BITS[self.framing]

    def marks(self) -> tuple[int, int]:
        high = self.high_water if self.high_water is not None else self.rx_buffer_bytes // 2
        low = self.low_water if self.low_water is not None else self.rx_buffer_bytes // 4
        if not 0 <= low < high <= self.rx_buffer_bytes:
            raise ValueError(f"need 0 <= low_water {low} < high_water {high} <= buffer")
        return high, low


class LineReader(asyncio.StreamReader):
    """The receive side of one connection: a stream that also counts every byte the sender's
    writes delivered to us (``received``) and can take at once everything the OS holds for us
    (``drain``), however late this event loop is."""

    def __init__(self, on_data: Callable[[], None]) -> None:
        super().__init__()
        self.received = 0
        self.fd: int | None = None  # the pty, device or socket descriptor: ``drain`` reads it
        self._on_data = on_data

    def feed_data(self, data: bytes) -> None:
        super().feed_data(data)
        self.received += len(data)
        self._on_data()

    def feed_eof(self) -> None:
        self.fd = None  # the transport closes the descriptor next: never read a reused number
        super().feed_eof()

    def set_exception(self, exc: BaseException) -> None:
        self.fd = None
        super().set_exception(exc)

    def drain(self) -> None:
        """Read what the OS holds now (the transport would at the loop's next pass). A pty read
        that finds nothing first pushes the kernel's pending input through (n_tty_read flushes
        the flip buffer), so afterwards every byte written before the call is counted."""
        while self.fd is not None:
            try:
                data = os.read(self.fd, 65536)
            except OSError:  # EAGAIN: all read; anything else the transport reports itself
                return
            if not data:
                return  # EOF: the transport sees it too
            self.feed_data(data)
