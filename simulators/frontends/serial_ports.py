"""Where the simulated DNC line is plugged in: a pty, an existing serial device or a TCP port
(``socket://``), one sender at a time, and closing them (the endpoints of ``SerialFrontend``)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import termios
import tty
from typing import Any

from simulators.frontends import cancel_tasks
from simulators.frontends.serial_line import LineReader


class SerialEndpoints:
    """The endpoints half of ``simulators.frontends.serial.SerialFrontend``: it opens the pty,
    device or TCP listener and hands each connection to the frontend's ``_session``."""

    _wake: asyncio.Event
    _fds: list[int]
    _pipes: list[asyncio.BaseTransport]
    _tasks: list[asyncio.Task]
    _server: asyncio.base_events.Server | None
    _session_lock: asyncio.Lock
    _closing: bool
    _writer: asyncio.StreamWriter | None
    _tcp_writer: asyncio.StreamWriter | None
    _session: Any  # SerialFrontend._session(reader, writer): one connection

    async def open_pty(self) -> str:
        """Create a pty pair; return the device path the DNC sender opens."""
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline: all byte values pass
        self._fds += [master, slave]  # keep the slave open: no EIO when the sender closes
        await self._attach_fd(master)
        return os.ttyname(slave)

    async def open_device(self, path: str) -> None:
        """Serve on an existing serial device (a USB-RS232 adapter, one end of a socat pair)."""
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        with contextlib.suppress(termios.error):
            tty.setraw(fd)
        self._fds.append(fd)
        await self._attach_fd(fd)

    async def _attach_fd(self, fd: int) -> None:
        loop = asyncio.get_running_loop()
        os.set_blocking(fd, False)  # LineReader.drain reads it too, and must never block
        reader = LineReader(self._wake.set)
        reader.fd = fd
        rt, _ = await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader),
                                             os.fdopen(os.dup(fd), "rb", 0))
        self._pipes.append(rt)
        wt, wp = await loop.connect_write_pipe(asyncio.streams.FlowControlMixin,
                                               os.fdopen(os.dup(fd), "wb", 0))
        writer = asyncio.StreamWriter(wt, wp, None, loop)
        self._tasks.append(asyncio.create_task(self._session(reader, writer)))

    async def open_tcp(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen for a ``socket://host:port`` sender (one at a time); return the bound port."""
        loop = asyncio.get_running_loop()
        # asyncio.start_server, with our counting reader
        self._server = await loop.create_server(
            lambda: asyncio.StreamReaderProtocol(LineReader(self._wake.set), self._on_client),
            host, port)
        return self._server.sockets[0].getsockname()[1]

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._session_lock.locked():
            writer.close()  # one DNC sender at a time, as on a real port
            return
        assert isinstance(reader, LineReader)
        reader.fd = writer.get_extra_info("socket").fileno()
        task = asyncio.current_task()
        assert task is not None
        self._tasks.append(task)  # close() cancels and awaits it with the other tasks
        self._tcp_writer = writer
        try:
            await self._session(reader, writer)
        except asyncio.CancelledError:
            # Python 3.11's start_server logs a cancelled client handler as an unhandled
            # error; a shutdown is not one.
            if not self._closing:
                raise
        finally:
            self._tcp_writer = None
            if task in self._tasks:
                self._tasks.remove(task)

    async def close(self) -> None:
        self._closing = True
        await cancel_tasks(self._tasks)
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await self._server.wait_closed()
        if self._writer is not None:
            self._writer.close()
        for pipe in self._pipes:
            pipe.close()
        for fd in self._fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds.clear()
