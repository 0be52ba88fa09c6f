"""Serial DNC sender: bytes in flight after an XOFF stay within ``tx_chunk_bytes`` (the control's
slack above its high-water mark), even when the event loop stalls; the receive buffer stays
bounded whatever the line sends."""

from __future__ import annotations

import asyncio
import time

import pytest

from drivers.base import LinkError
from drivers.serial.link import XOFF, XON, SerialDncLink, _DncProtocol
from drivers.serial.schema import SerialLinkConfig

BAUD, CPS = 115200, 11520.0  # 8N1: 10 bits per character
BUDGET = 16


class _UartModel:
    """Stands for the port: records every write and, like a UART shifting bytes out at the
    baud rate, how many bytes were written but not yet through the line at that moment."""

    def __init__(self, proto: _DncProtocol, xoff_at_write: int | None = None) -> None:
        self.proto = proto
        self.line_t = 0.0
        self.in_flight: list[float] = []
        self.writes_during_xoff = 0
        self.xoff_at_write = xoff_at_write

    def write(self, data: bytes) -> None:
        now = time.monotonic()
        if not self.proto.xon.is_set():
            self.writes_during_xoff += 1
        self.line_t = max(self.line_t, now) + len(data) / CPS
        self.in_flight.append((self.line_t - now) * CPS)
        if self.xoff_at_write is not None and len(self.in_flight) == self.xoff_at_write:
            self.proto.data_received(bytes([XOFF]))  # the control's buffer reached high water
            asyncio.get_running_loop().call_later(0.02, self.proto.data_received, bytes([XON]))

    def get_write_buffer_size(self) -> int:
        return 0

    def close(self) -> None:
        pass


def _link(model_xoff_at: int | None = None) -> tuple[SerialDncLink, _UartModel]:
    link = SerialDncLink(SerialLinkConfig(transport="serial", url="socket://127.0.0.1:1",
                                          baudrate=BAUD, framing="8N1", tx_chunk_bytes=BUDGET))
    proto = _DncProtocol()
    uart = _UartModel(proto, model_xoff_at)
    link._proto, link._transport = proto, uart  # type: ignore[assignment]
    return link, uart


async def test_a_loop_stall_never_puts_more_than_the_budget_in_flight():
    # The flaky e2e overflow: after the loop was blocked (the control's computation, GC, a
    # busy CPU), the sender caught up with a burst of two chunks; each stall put one more
    # chunk in flight than the line had carried, and everything in flight still reaches the
    # control after its XOFF. The stall here is the stimulus, not a synchronisation.
    link, uart = _link()
    loop = asyncio.get_running_loop()
    for k in range(5):
        loop.call_later(0.01 + 0.02 * k, time.sleep, 0.015)
    await asyncio.wait_for(link._stream(bytes(1500)), 10)
    assert len(uart.in_flight) >= 1500 // BUDGET
    worst = max(uart.in_flight)
    assert worst <= BUDGET + 1e-6, f"{worst:.1f} bytes in flight > tx_chunk_bytes {BUDGET}"


async def test_nothing_is_written_between_xoff_and_xon():
    link, uart = _link(model_xoff_at=5)
    await asyncio.wait_for(link._stream(bytes(400)), 10)
    assert link._proto.xoff_count == 1
    assert uart.writes_during_xoff == 0


def test_overlong_line_is_discarded_and_the_buffer_stays_bounded(caplog):
    from drivers.serial.link import MAX_LINE_BYTES

    proto = _DncProtocol()
    block = b"x" * 65536
    for _ in range(20 * 1024 * 1024 // len(block)):  # 20 MB without a newline
        proto.data_received(block)
        assert len(proto._partial) <= MAX_LINE_BYTES
    assert "longer than" in caplog.text and caplog.text.count("longer than") == 1
    proto.data_received(b"tail of the noise\nRUMBA REQUEST MILL1\n")  # the line recovers
    assert proto.requests.get_nowait() == ("MILL1", "RUMBA REQUEST MILL1")


async def test_overlong_line_during_a_run_ends_the_run_with_the_reason():
    from drivers.serial.link import MAX_LINE_BYTES

    proto = _DncProtocol()
    proto.running = True
    proto.data_received(b"RUMBA 1 " + b"9" * (MAX_LINE_BYTES + 10))
    item = proto.lines.get_nowait()
    assert isinstance(item, LinkError)
    assert f"longer than {MAX_LINE_BYTES} bytes" in str(item)
    proto.data_received(b"\nRUMBA 1 2\n")  # the next line is a line again
    assert proto.lines.get_nowait() == "RUMBA 1 2"


@pytest.mark.parametrize("cut", [1, 7, 1023, 1024])
def test_lines_split_anywhere_are_reassembled(cut):
    proto = _DncProtocol()
    proto.running = True
    data = b"A" * 1000 + b"\r\n" + bytes([XOFF]) + b"B\n"
    proto.data_received(data[:cut])
    proto.data_received(data[cut:])
    assert [proto.lines.get_nowait(), proto.lines.get_nowait()] == ["A" * 1000, "B"]
    assert proto.xoff_count == 1


async def test_at_most_max_write_bytes_per_loop_pass_at_921600():
    # A 921 600-baud budget of 128 bytes: a peer pacing its reads on the loop's ≈ 1 ms timer
    # (the pty simulator takes ≈ 64 per tick) fell behind when handed the whole budget per
    # tick, and its backlog arrived after XOFF (e2e overflow).
    from drivers.serial.link import MAX_WRITE_BYTES

    link = SerialDncLink(SerialLinkConfig(transport="serial", url="socket://127.0.0.1:1",
                                          baudrate=921600, framing="8N1", tx_chunk_bytes=128))
    proto = _DncProtocol()
    passes = [0]
    per_pass: dict[int, int] = {}

    class Port:
        def write(self, data: bytes) -> None:
            per_pass[passes[0]] = per_pass.get(passes[0], 0) + len(data)

        def get_write_buffer_size(self) -> int:
            return 0

    loop = asyncio.get_running_loop()

    counting = [True]

    def tick() -> None:  # counts passes through the event loop
        passes[0] += 1
        if counting[0]:
            loop.call_soon(tick)

    loop.call_soon(tick)
    link._proto, link._transport = proto, Port()  # type: ignore[assignment]
    loop.call_later(0.002, time.sleep, 0.01)  # a stall: the line is idle, the budget free
    try:
        await asyncio.wait_for(link._stream(bytes(4000)), 10)
    finally:
        counting[0] = False
    assert sum(per_pass.values()) == 4000
    assert max(per_pass.values()) <= MAX_WRITE_BYTES


def test_a_cut_tape_never_ends_inside_a_multi_line_if() -> None:
    """An aborted stream finishes its line and every Siemens IF / LinuxCNC o-if it opened: a
    tape ending between IF and ENDIF is a syntax alarm at the control (seen: "no matching
    ELSEIF/ELSE/ENDIF"), not a stop; a Fanuc IF … GOTO is one line."""
    from drivers.serial.link import cut_point

    siemens = b'%\nN1 G0 X1\nIF R105==0\nMSG("miss")\nENDIF\nN2 G1 X2\n%\n'
    for i, last in ((3, b"N1 G0 X1\n"), (12, b"ENDIF\n"), (20, b"ENDIF\n"), (31, b"ENDIF\n"),
                    (40, b"N2 G1 X2\n")):
        assert siemens[:cut_point(siemens, i)].endswith(last), i
    lcnc = b"N1 G38.2 X1\no10001 if [#5070 EQ 0]\n(abort,miss)\no10001 endif\nN2 G0 X0\n"
    assert lcnc[:cut_point(lcnc, 14)].endswith(b"o10001 endif\n")
    fanuc = b"N1 G31 X1\nIF [#5061 EQ 0] GOTO 9\nN2 G0 X0\n"
    assert fanuc[:cut_point(fanuc, 12)] == b"N1 G31 X1\nIF [#5061 EQ 0] GOTO 9\n"
