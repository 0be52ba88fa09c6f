"""Serial DNC: our driver against the simulator's serial front-end and the real VirtualController
over real ptys and TCP (``socket://``), with real probing programs and the dialect's parser."""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import socket
import subprocess
import threading
import time

import pytest
import serial

from benchmarks.rigs.transport_sim import first_touch_of, hits_until_miss, latched_equal, real_setup
from contracts.result_lines import DIALECT_NAMES
from drivers.base import ControllerAlarm, LinkError
from drivers.serial.link import SerialDncLink, frame_program
from drivers.serial.schema import SerialLinkConfig
from simulators.faults import Fault, FaultPlan
from simulators.frontends.serial import SerialFrontend, SerialSettings


def link_for(url: str, **kw) -> SerialDncLink:
    return SerialDncLink(SerialLinkConfig(transport="serial", url=url, **kw))


async def collect(link: SerialDncLink, job, timeout: float = 30) -> list:
    async def go() -> list:
        return [h async for h in link.run(job)]
    return await asyncio.wait_for(go(), timeout)


def assert_hits_match(hits, vc, job) -> None:
    latched_equal(hits, vc, job, tol_mm=0.5e-4 + 1e-9)  # DPRNT prints 4 decimals


async def test_xonxoff_sender_never_overflows_256_byte_buffer_at_115200():
    # time scale 0.08: the control executes slower than 115 200 baud delivers, so the
    # 256-byte buffer fills and XOFF/XON must regulate the stream.
    vc, job = real_setup("fanuc", time_scale=0.08)
    fe = SerialFrontend(vc, SerialSettings(baudrate=115200, framing="7E1", rx_buffer_bytes=256))
    link = link_for(await fe.open_pty(), baudrate=115200, framing="7E1")  # Fanuc's default
    await link.connect()
    try:
        hits = await collect(link, job)
        assert await vc.wait_done(10) == "done"
    finally:
        await link.close()
        await fe.close()
    assert fe.alarms == []
    assert fe.xoff_sent > 0, "the buffer never reached high water: the test proves nothing"
    assert fe.max_fill <= 256
    assert_hits_match(hits, vc, job)


async def test_sender_ignoring_xoff_gets_overflow_alarm_reported():
    vc, job = real_setup("fanuc", time_scale=0.08)
    fe = SerialFrontend(vc, SerialSettings(baudrate=115200, framing="8N1", rx_buffer_bytes=256))
    link = link_for(await fe.open_pty(), baudrate=115200, framing="8N1", xonxoff=False)
    await link.connect()
    try:
        with pytest.raises(ControllerAlarm, match="overflow"):
            await collect(link, job)
    finally:
        await link.close()
        await fe.close()
    assert len(fe.alarms) == 1 and "overflow" in fe.alarms[0]
    assert vc.state != "done" and len(vc.touches) < job.touch_count


async def test_socket_url_7e1_crlf_and_probe_miss():
    vc, job = real_setup("fanuc", errors={"absent_balls": ["B1"]})
    miss = first_touch_of(job, "B1")
    fe = SerialFrontend(vc, SerialSettings(baudrate=38400, framing="7E1", eol="CRLF"))
    port = await fe.open_tcp()
    link = link_for(f"socket://127.0.0.1:{port}", baudrate=38400, framing="7E1", eol="CRLF")
    await link.connect()
    try:
        got = await hits_until_miss(link, job, miss)
    finally:
        await link.close()
        await fe.close()
    assert got[-1].ball == "B1"
    assert vc.state == "alarm" and "3001" in vc.alarm


@pytest.mark.parametrize(("kind", "time_scale", "link_kw", "match"), [
    ("missing_xon", 0.08, {"xoff_timeout_s": 0.5}, "XOFF"),
    # a garbled result line is a link error, never a wrong number
    ("garbled", 0.0, {}, "garbled"),
])
async def test_line_fault_ends_with_link_error(kind, time_scale, link_kw, match):
    vc, job = real_setup("fanuc", time_scale=time_scale)
    vc.faults = FaultPlan([Fault(kind=kind, at_block=1)])
    fe = SerialFrontend(vc, SerialSettings(baudrate=115200, framing="8N1"))
    link = link_for(await fe.open_pty(), baudrate=115200, framing="8N1", **link_kw)
    await link.connect()
    try:
        with pytest.raises(LinkError, match=match):
            await collect(link, job)
    finally:
        await link.close()
        await fe.close()


async def test_disconnect_fault_on_tcp_is_a_link_error():
    vc, job = real_setup("fanuc", time_scale=0.02)
    vc.faults = FaultPlan([Fault(kind="disconnect", at_block=40)])
    fe = SerialFrontend(vc, SerialSettings(baudrate=115200, framing="8N1"))
    port = await fe.open_tcp()
    link = link_for(f"socket://127.0.0.1:{port}", baudrate=115200, framing="8N1")
    await link.connect()
    try:
        with pytest.raises(LinkError, match="closed"):
            await collect(link, job)
        for _ in range(100):  # the control notices the dead line
            if fe.alarms:
                break
            await asyncio.sleep(0.02)
    finally:
        await link.close()
        await fe.close()
    assert fe.alarms and "DNC stream interrupted" in fe.alarms[-1]
    assert vc.state != "done"  # the program did not silently complete


def test_framing_adds_percent_and_rejects_8bit_on_7e1():
    assert frame_program("G0 X1\nM30", "CRLF", True) == b"%\r\nG0 X1\r\nM30\r\n%\r\n"
    assert frame_program("%\nG0 X1\n%\n", "LF", True) == b"%\nG0 X1\n%\n"
    with pytest.raises(LinkError, match="line 2"):
        frame_program("G0 X1\n(CAL\u00e9)", "LF", True)


async def test_unreachable_port_is_one_clear_error(tmp_path):
    link = link_for(str(tmp_path / "nope"))
    with pytest.raises(LinkError, match="cannot open"):
        await link.connect()


class _Rfc2217Server:
    """pyserial's RFC 2217 port manager in front of a ``socket://`` port: a serial device
    server (as in a shop's Moxa/Lantronix box), in threads as pyserial's example server."""

    def __init__(self, port_url: str) -> None:
        from serial import rfc2217

        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.ser = serial.serial_for_url(port_url, timeout=0.05)
        self._rfc2217 = rfc2217
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._serve, daemon=True)]
        self.threads[0].start()

    def _serve(self) -> None:
        conn, _ = self.listener.accept()
        conn.settimeout(0.05)
        lock = threading.Lock()

        def send(data: bytes) -> None:
            with lock:
                conn.sendall(data)
        manager = self._rfc2217.PortManager(self.ser, type("C", (), {"write": staticmethod(send)}))

        def to_net() -> None:
            while not self.stop.is_set():
                try:
                    data = self.ser.read(self.ser.in_waiting or 1)
                except serial.SerialException:
                    return  # the simulator hung up (it may close before this bridge)
                if data:
                    send(b"".join(manager.escape(data)))
        self.threads.append(threading.Thread(target=to_net, daemon=True))
        self.threads[-1].start()
        while not self.stop.is_set():
            try:
                data = conn.recv(1024)
            except TimeoutError:
                continue
            if not data:
                break
            self.ser.write(b"".join(manager.filter(data)))
        conn.close()

    def close(self) -> None:
        self.stop.set()
        self.listener.close()
        for t in self.threads:
            t.join(2)
        self.ser.close()


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # pyserial's rfc2217 threads
async def test_rfc2217_serial_server_url():
    vc, job = real_setup("fanuc", time_scale=0.02)
    fe = SerialFrontend(vc, SerialSettings(baudrate=115200, framing="8N1"))
    port = await fe.open_tcp()
    server = _Rfc2217Server(f"socket://127.0.0.1:{port}")
    link = link_for(f"rfc2217://127.0.0.1:{server.port}", baudrate=115200, framing="8N1")
    try:
        await link.connect()
        hits = await collect(link, job)
    finally:
        await link.close()
        await fe.close()
        server.close()
    assert_hits_match(hits, vc, job)
    assert fe.alarms == []


@pytest.mark.peer
async def test_socat_pty_pair_carries_the_protocol(tmp_path):
    socat = shutil.which("socat")
    if socat is None:
        pytest.skip("socat not installed (.ci/install-peers.sh installs it)")
    a, b = tmp_path / "ttyA", tmp_path / "ttyB"
    proc = subprocess.Popen([socat, f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 5
        while not (a.exists() and b.exists()):
            assert time.monotonic() < deadline, "socat did not create its ptys"
            await asyncio.sleep(0.02)
        vc, job = real_setup("fanuc", time_scale=0.05)
        fe = SerialFrontend(vc, SerialSettings(baudrate=115200, framing="8N1"))
        await fe.open_device(str(b))  # the controller on socat's end B, the daemon on end A
        link = link_for(str(a), baudrate=115200, framing="8N1")
        await link.connect()
        try:
            hits = await collect(link, job)
            assert await vc.wait_done(10) == "done"
        finally:
            await link.close()
            await fe.close()
        assert_hits_match(hits, vc, job)
        assert fe.alarms == [] and fe.xoff_sent > 0  # flow control crossed socat too
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(5)


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
async def test_every_dialect_result_lines_over_dnc(dialect):
    """DPRNT (Fanuc/Haas), WRITE (Siemens), FN 16 F-PRINT (Heidenhain), LOG (LinuxCNC): the
    program's own result lines come back on the port and decode to the latched values."""
    vc, job = real_setup(dialect)
    fe = SerialFrontend(vc, SerialSettings(baudrate=921600, framing="8N1"))
    port = await fe.open_tcp()
    link = link_for(f"socket://127.0.0.1:{port}", baudrate=921600, framing="8N1")
    await link.connect()
    try:
        hits = await collect(link, job)
    finally:
        await link.close()
        await fe.close()
    assert_hits_match(hits, vc, job)


@pytest.mark.parametrize("sender_hangs_up_first", [False, True])
async def test_close_with_tcp_sender_leaves_nothing_running(sender_hangs_up_first):
    # A simulator stopped just as (or while) a DNC sender is connected must leave no handler
    # task behind: one cancelled later by the loop's teardown makes Python 3.11 log an
    # "Exception in callback" traceback (seen at the end of bench_e2e).
    vc, _ = real_setup("fanuc")
    fe = SerialFrontend(vc, SerialSettings(baudrate=115200, framing="8N1"))
    loop_errors: list[dict] = []
    asyncio.get_running_loop().set_exception_handler(lambda _l, ctx: loop_errors.append(ctx))
    port = await fe.open_tcp()
    _reader, writer = await asyncio.open_connection("127.0.0.1", port)
    for _ in range(100):  # the handler is running once it holds the session
        if fe._session_lock.locked():
            break
        await asyncio.sleep(0.01)
    assert fe._session_lock.locked()
    writer.write(b"%\nG90\n")
    await writer.drain()
    if sender_hangs_up_first:
        writer.close()
        await asyncio.sleep(0.02)
    await fe.close()
    left = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
    assert left == []
    writer.close()
    await asyncio.sleep(0.05)  # let done-callbacks run
    assert loop_errors == []
