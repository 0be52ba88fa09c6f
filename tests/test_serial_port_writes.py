"""The DNC link's serial port writes (drivers/serial/transport.py) on a real pty whose reading end
stalls then catches up, as a simulated control on a loaded machine does: once the backlog has
gone out, no callback is left polling the port (the loop's exception handler never called, no
traceback), and a write to a full port never blocks the event loop."""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import os
import select
import struct
import termios
import threading
import time
import tty

import pytest

from drivers.serial.link import SerialDncLink
from drivers.serial.schema import SerialLinkConfig


class Pty:
    """A pty pair in raw mode: the link opens the slave's path, the test reads the master."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.received = bytearray()

    def read_all(self) -> None:
        """Read what the master holds now (non-blocking)."""
        while select.select([self.master], [], [], 0)[0]:
            data = os.read(self.master, 65536)
            if not data:
                return
            self.received += data

    def _fill_once(self) -> int:
        fd = os.open(self.path, os.O_WRONLY | os.O_NOCTTY | os.O_NONBLOCK)
        n = 0
        try:
            while True:
                try:
                    n += os.write(fd, b"f" * 512)
                except BlockingIOError:
                    return n
        finally:
            os.close(fd)

    def _queued(self) -> int:
        return struct.unpack("i", fcntl.ioctl(self.master, termios.FIONREAD, b"\0" * 4))[0]

    def fill(self) -> int:
        """Write on the slave (a second descriptor) until the pty takes no more byte. The
        kernel moves what a write took into the master's read buffer later (a work queue), which
        frees room again: so until a pass takes nothing and the master's queue has not moved
        for 0.1 s (a fill that returned at the first EAGAIN once left room for the test's
        write on a loaded box)."""
        n, stable, last = 0, 0, -1
        while stable < 5:
            took = self._fill_once()
            n += took
            time.sleep(0.02)
            queued = self._queued()
            stable = stable + 1 if took == 0 and queued == last else 0
            last = queued
        return n

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


@pytest.fixture
def pty_pair():
    p = Pty()
    yield p
    p.close()


@pytest.fixture
def loop_errors():
    """Everything that reaches the event loop's exception handler (a callback's traceback);
    ``_connected`` installs the handler in the test's loop."""
    return []


async def _connected(path: str, seen: list[dict]) -> SerialDncLink:
    asyncio.get_running_loop().set_exception_handler(lambda _loop, ctx: seen.append(ctx))
    link = SerialDncLink(SerialLinkConfig(transport="serial", url=path, baudrate=115200,
                                          framing="8N1"))
    await link.connect()
    await asyncio.sleep(0)  # connection_made and the reader registration run
    return link


async def test_a_backlog_that_drained_leaves_no_callback_polling_the_port(pty_pair, loop_errors):
    # More than the pty holds: part is written at once, the rest waits for the reader.
    link = await _connected(pty_pair.path, loop_errors)
    transport = link._transport
    payload = bytes(range(32, 127)) * 400  # 38 000 bytes
    try:
        transport.write(payload)
        assert transport.get_write_buffer_size() > 0, "the pty took it all: nothing tested"
        while len(pty_pair.received) < len(payload):
            await asyncio.sleep(0.005)
            pty_pair.read_all()
        assert bytes(pty_pair.received) == payload
        for _ in range(50):  # passes through the loop with the port writable and nothing to send
            await asyncio.sleep(0)
        assert loop_errors == [], loop_errors[:1]
        assert not transport._has_writer
        # and the port still writes afterwards
        transport.write(b"N10 G01 X1\n")
        await asyncio.sleep(0)
        pty_pair.read_all()
        assert bytes(pty_pair.received).endswith(b"N10 G01 X1\n")
    finally:
        await link.close()
    assert loop_errors == [], loop_errors[:1]


async def test_a_write_to_a_full_port_returns_at_once_and_goes_out_when_read(pty_pair,
                                                                            loop_errors):
    link = await _connected(pty_pair.path, loop_errors)
    transport = link._transport
    try:
        pty_pair.fill()
        # The reader wakes up later, in its own thread (a stalled control catching up).
        release = threading.Event()
        reader = threading.Thread(target=lambda: (release.wait(5), pty_pair.read_all()))
        reader.start()
        try:
            transport.write(b"%\n")
            # Returned without sending: buffered for the writer callback. (pyserial's own
            # write retries EAGAIN in a loop here, holding the event loop until the reader
            # ran, and came back with the buffer empty.)
            assert transport.get_write_buffer_size() == 2
        finally:
            release.set()
            reader.join()
        while not bytes(pty_pair.received).endswith(b"%\n"):
            await asyncio.sleep(0.005)
            pty_pair.read_all()
        for _ in range(20):
            await asyncio.sleep(0)
        assert transport.get_write_buffer_size() == 0 and not transport._has_writer
    finally:
        await link.close()
    assert loop_errors == [], loop_errors[:1]


async def test_a_run_through_a_control_that_stalls_reading_ends_without_a_traceback(
        loop_errors, caplog):
    # The simulated control's receive side stops reading the pty mid-program (its process
    # descheduled on a loaded machine): the link keeps writing at the line rate until the pty
    # is full, then waits; the control catches up (XOFF/XON on the backlog) and the run ends
    # with every hit; nothing logged a traceback meanwhile or after.
    from benchmarks.rigs.transport_sim import latched_equal, real_setup
    from simulators.frontends.serial import SerialFrontend, SerialSettings

    vc, job = real_setup("fanuc", poses=((0, 0), (30, 60), (0, 180), (-30, 300)))
    fe = SerialFrontend(vc, SerialSettings(baudrate=115200, framing="8N1",
                                           rx_buffer_bytes=4096))
    link = await _connected(await fe.open_pty(), loop_errors)
    try:
        run = asyncio.ensure_future(_collect(link, job))
        while link.bytes_sent < 2000:
            await asyncio.sleep(0.002)
        fe._pipes[0].pause_reading()  # the control's side of the pty stops reading
        while not link._transport.get_write_buffer_size():  # the pty is full
            assert not run.done(), run.exception()
            await asyncio.sleep(0.005)
        fe._pipes[0].resume_reading()
        hits = await asyncio.wait_for(run, 120)
        assert await vc.wait_done(30) == "done"
        for _ in range(50):
            await asyncio.sleep(0)
    finally:
        await link.close()
        await fe.close()
    latched_equal(hits, vc, job, tol_mm=0.5e-4 + 1e-9)
    assert fe.alarms == []
    assert loop_errors == [], loop_errors[:1]
    assert not [r for r in caplog.records if r.exc_info], caplog.records[:1]


async def _collect(link: SerialDncLink, job) -> list:
    return [h async for h in link.run(job)]
