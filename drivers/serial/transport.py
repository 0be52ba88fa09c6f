"""The serial port's asyncio transport: serial_asyncio_fast's ``SerialTransport`` with its write
path made non-blocking and its writer callback removed once the buffer has drained.

serial_asyncio_fast 0.16 leaves two faults in the write path of a device port (a tty, a pty):

* After a partial write it registers a writer callback on the descriptor and buffers the rest;
  when ``_write_ready`` has written that rest, nothing removes the callback. A tty is almost
  always writable, so the loop calls ``_write_ready`` again at once on an empty buffer, whose
  ``assert data`` fails: a traceback logged by the loop's exception handler on every pass
  through the loop, for as long as the port stays open (a DNC daemon's log grew by 88 MB in
  7.5 minutes, at 15 % CPU, long after its run had ended). The fault is open upstream
  (home-assistant-libs/pyserial-asyncio-fast pull request 36).
* It writes through pyserial's ``Serial.write``, which on ``EAGAIN`` with a zero write timeout
  retries at once, in a loop, until the descriptor takes a byte: a port whose peer stopped
  reading (a control whose receive side is stalled) blocks the whole event loop.

Here a write is one ``os.write`` on the port's descriptor: what it takes is sent, the rest waits
in the buffer for the writer callback, and the callback is removed as soon as the buffer is
empty. A write error ends the transport through ``connection_lost`` (the link reports the line
closed), never as a traceback. ``socket://`` URLs keep asyncio's own socket transport; ports
without a file descriptor (``rfc2217://``) get ``ThreadTransport``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import threading
import urllib.parse
from collections.abc import Callable
from functools import partial
from typing import Any

import serial
import serial_asyncio_fast

log = logging.getLogger("rumba.serial")


class SerialPortTransport(serial_asyncio_fast.SerialTransport):
    """A serial device's transport whose writes never block the loop and whose writer callback
    is registered only while bytes wait to be written."""

    def _write_ready(self) -> None:
        data = b"".join(self._write_buffer)
        self._write_buffer.clear()
        if not data:  # nothing left: stop being called on every writable pass
            self._remove_writer()
            if self._closing:
                self._close()
            return
        self._write_data(data)
        self._maybe_resume_protocol()

    def _write_data(self, data: bytes | bytearray | memoryview) -> None:
        try:
            n = os.write(self._serial.fileno(), data)
        except (BlockingIOError, InterruptedError):
            n = 0  # the peer has not read what the descriptor holds: wait for room
        except OSError as e:  # EIO: the other end of the line is gone
            self._fatal_error(e, "write error on the serial port")
            return
        if n == len(data):
            self._remove_writer()
            if self._closing:
                self._close()
            return
        self._write_buffer.append(bytes(data[n:]))
        self._maybe_pause_protocol()
        self._ensure_writer()

    def _fatal_error(self, exc: BaseException,
                     message: str = "Fatal error on serial transport") -> None:
        # The protocol hears of it through connection_lost (the link: "serial line closed");
        # one line in the log, not the loop exception handler's traceback.
        log.warning("serial: %s: %s", message, exc)
        self._abort(exc)


class ThreadTransport:
    """For ports without a file descriptor (``rfc2217://``): a reader thread, executor writes."""

    def __init__(self, ser: serial.SerialBase, proto: asyncio.Protocol,
                 loop: asyncio.AbstractEventLoop) -> None:
        self.ser, self.proto, self.loop = ser, proto, loop
        self._stop = threading.Event()
        self._writer = concurrent.futures.ThreadPoolExecutor(1, "rumba-serial-tx")
        self._thread = threading.Thread(target=self._read, daemon=True, name="rumba-serial-rx")
        self._thread.start()

    def _read(self) -> None:
        try:
            while not self._stop.is_set():
                data = self.ser.read(max(1, self.ser.in_waiting))
                if data:
                    self.loop.call_soon_threadsafe(self.proto.data_received, data)
        except Exception as e:  # the port went away: report it on the loop
            if not self._stop.is_set():
                self.loop.call_soon_threadsafe(self.proto.connection_lost, e)

    def write(self, data: bytes) -> None:
        self._writer.submit(self.ser.write, data)  # one writer thread: order is kept

    def close(self) -> None:
        self._stop.set()
        self._writer.shutdown(wait=False, cancel_futures=True)
        with contextlib.suppress(Exception):
            self.ser.close()


async def create_serial_connection(
        loop: asyncio.AbstractEventLoop, protocol_factory: Callable[[], asyncio.Protocol],
        url: str, **kwargs: Any) -> tuple[asyncio.BaseTransport, asyncio.Protocol]:
    """serial_asyncio_fast's ``create_serial_connection`` with ``SerialPortTransport`` for a
    device path (pyserial's ``serial_for_url`` opens and configures the port)."""
    if urllib.parse.urlparse(url).scheme == "socket":
        return await serial_asyncio_fast.create_serial_connection(loop, protocol_factory, url,
                                                                  **kwargs)
    port = await loop.run_in_executor(None, partial(serial.serial_for_url, url, **kwargs))
    try:
        port.fileno()
    except (AttributeError, NotImplementedError, serial.SerialException):
        port.close()
        raise ValueError(f"{url}: the port has no file descriptor to wait on") from None
    protocol = protocol_factory()
    return SerialPortTransport(loop, protocol, port), protocol
