"""The serial simulator's overflow alarm blames the sender only for what it wrote after our XOFF
could reach it.

The simulator runs here in its own thread and event loop, as ``rumba sim --serve serial`` runs in
its own process. Its loop is frozen, as a loaded machine leaves a process unscheduled, while the
DNC sender streams into the pty (or TCP socket) at the line rate: nobody reads, no XOFF can go
out. Resumed, the simulator finds that backlog waiting. The sender wrote all of it before our
XOFF: no alarm, and its run completes. A sender that writes on after it has read our XOFF still
gets the overflow alarm. The simulated control holds at its first block (a feed hold) so that
the backlog cannot be executed away. Every step waits for an event (bytes written, an XOFF
read, a hold on the line, an alarm), never for a duration."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import threading
import tty
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

import pytest

from benchmarks.rigs.transport_sim import latched_equal, real_setup
from drivers.serial.link import XOFF, SerialDncLink, frame_program
from drivers.serial.schema import SerialLinkConfig
from simulators.faults import Fault, FaultPlan
from simulators.frontends.serial import SerialFrontend, SerialSettings

T = TypeVar("T")
BAUD = 115200
BUFFER = 256
BACKLOG = 2048
"""Bytes the sender writes while the simulator is frozen: far more than the buffer and the
control's look-ahead (9 blocks) take, far less than a pty holds (≈ 16 kB)."""


class SimLoop:
    """An event loop in its own thread: the simulator's process."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self._thaw: threading.Event | None = None

    async def run(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run ``coro`` on the simulator's loop; its result."""
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, self.loop))

    def freeze(self) -> None:
        """Stop the simulator's loop dead until ``thaw``; returns once it is stopped."""
        frozen, self._thaw = threading.Event(), threading.Event()
        thaw = self._thaw

        def block() -> None:
            frozen.set()
            thaw.wait()

        self.loop.call_soon_threadsafe(block)
        frozen.wait()

    def thaw(self) -> None:
        if self._thaw is not None:
            self._thaw.set()

    def close(self) -> None:
        self.thaw()

        async def cancel_the_rest() -> None:  # nothing left pending for the loop's teardown
            rest = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for t in rest:
                t.cancel()
            await asyncio.gather(*rest, return_exceptions=True)

        asyncio.run_coroutine_threadsafe(cancel_the_rest(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


async def until(condition: Callable[[], object], what: str) -> None:
    """Wait for ``condition`` (state of the other thread, looked at each millisecond); the
    timeout only turns a hang into a failure."""
    try:
        async with asyncio.timeout(30):
            while not condition():
                await asyncio.sleep(0.001)
    except TimeoutError:
        raise AssertionError(f"never happened: {what}") from None


async def _held_control(fe_settings: SerialSettings, transport: str
                        ) -> tuple[Any, Any, SerialFrontend, str]:
    """On the simulator's loop: a control that holds at its first block, behind a pty or a
    TCP serial server; the URL the sender opens."""
    vc, job = real_setup("fanuc")
    vc.faults = FaultPlan([Fault(kind="feed_hold", at_block=1)])  # until cycle start
    fe = SerialFrontend(vc, fe_settings)
    if transport == "pty":
        return vc, job, fe, await fe.open_pty()
    return vc, job, fe, f"socket://127.0.0.1:{await fe.open_tcp()}"


async def _collect(link: SerialDncLink, job: Any) -> list:
    return [h async for h in link.run(job)]


async def _cancelled(task: asyncio.Task) -> None:
    task.cancel()  # no-op once done
    with contextlib.suppress(asyncio.CancelledError, Exception):
        await task


class RawSender:
    """A DNC sender that ignores XOFF: it writes what the test gives it, when the test says, and
    only notes the XOFF it reads (the driver with ``xonxoff: false`` ignores XOFF too, but it
    streams on its own clock: when a loaded machine delays the simulator long enough, it has
    written its whole program before our XOFF went out, which ignores nothing)."""

    def __init__(self, url: str) -> None:
        self.sock: socket.socket | None = None
        if url.startswith("socket://"):
            host, port = url.removeprefix("socket://").rsplit(":", 1)
            self.sock = socket.create_connection((host, int(port)))
            self.fd = self.sock.fileno()
        else:
            self.fd = os.open(url, os.O_RDWR | os.O_NOCTTY)
            tty.setraw(self.fd)
        os.set_blocking(self.fd, False)
        self.xoff_seen = 0

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:  # a pty or socket takes kilobytes: this never waits here
            view = view[os.write(self.fd, view):]

    def read_flow(self) -> int:
        """Read what the control sent; the number of XOFF so far."""
        with contextlib.suppress(BlockingIOError):
            while data := os.read(self.fd, 4096):
                self.xoff_seen += data.count(XOFF)
        return self.xoff_seen

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        else:
            os.close(self.fd)


@pytest.mark.parametrize("transport", ["pty", "socket"])
async def test_backlog_written_while_the_simulator_was_frozen_is_no_overflow(transport):
    sim = SimLoop()
    settings = SerialSettings(baudrate=BAUD, framing="8N1", rx_buffer_bytes=BUFFER)
    try:
        vc, job, fe, url = await sim.run(_held_control(settings, transport))
        link = SerialDncLink(SerialLinkConfig(transport="serial", url=url, baudrate=BAUD,
                                              framing="8N1"))
        await link.connect()
        sim.freeze()
        run = asyncio.create_task(
            asyncio.wait_for(_collect(link, job), 60))  # the bound only turns a hang to a fail
        try:
            await until(lambda: link.bytes_sent >= BACKLOG, f"{BACKLOG} bytes written")
            sim.thaw()
            # The simulator caught up, sent XOFF, the sender stopped: what it had written
            # before waits on the line, the buffer never overflows, nobody is blamed.
            await until(lambda: fe.line_holds or fe.alarms, "backlog held or an alarm")
            assert fe.alarms == []
            assert fe.max_fill <= BUFFER
            await sim.run(vc.start())  # cycle start: the control drains the line
            hits = await run
            latched_equal(hits, vc, job, tol_mm=0.5e-4 + 1e-9)
            assert await sim.run(vc.wait_done(10)) == "done"
            assert fe.alarms == [] and fe.max_fill <= BUFFER
            assert link._proto is not None and link._proto.xoff_count >= 1
        finally:
            sim.thaw()
            await _cancelled(run)
            await link.close()
            await sim.run(fe.close())
    finally:
        sim.close()


@pytest.mark.parametrize("transport", ["pty", "socket"])
async def test_writing_on_after_the_xoff_is_still_an_overflow(transport):
    sim = SimLoop()
    settings = SerialSettings(baudrate=BAUD, framing="8N1", rx_buffer_bytes=BUFFER)
    slack = BUFFER - settings.marks()[0]
    try:
        _vc, job, fe, url = await sim.run(_held_control(settings, transport))
        sender = RawSender(url)
        program = frame_program(job.text, "LF", seven_bit=False)
        try:
            sim.freeze()
            sender.write(program[:BACKLOG])  # written while nobody read: as above
            sim.thaw()
            await until(sender.read_flow, "an XOFF at the sender")
            await until(lambda: fe.line_holds or fe.alarms, "backlog held or an alarm")
            assert fe.alarms == []  # the backlog alone is no violation
            # Now the sender has read the XOFF, and writes on: more than the slack above the
            # high-water mark, the most an honest sender has in flight when the XOFF comes.
            sender.write(program[BACKLOG:BACKLOG + 2 * slack])
            await until(lambda: fe.alarms, "the overflow alarm")
            assert fe.alarms == [f"serial receive buffer overflow ({BUFFER} bytes): the sender "
                                 "ignored XOFF"]
        finally:
            sim.thaw()
            sender.close()
            await sim.run(fe.close())
    finally:
        sim.close()
