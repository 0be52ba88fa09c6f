"""The simulated control's flow control sends its state, never a stale one: an XON
decided when the receive buffer drained is dropped when an XOFF went out before it could be
sent (bytes held on the line, woken by that room, refilled the buffer past the high mark first).
Sent after that XOFF it freed the sender while the control counted the sender's next bytes as
written after XOFF: "serial receive buffer overflow: the sender ignored XOFF" in a loaded run of
the stop matrix."""

from __future__ import annotations

import asyncio

from benchmarks.rigs.rig_helpers import make_truth
from drivers.serial.lines import XOFF, XON
from simulators.controller import VirtualController
from simulators.frontends.serial import SerialFrontend


class Line:
    """The control's side of the line: what it wrote, in order."""

    def __init__(self) -> None:
        self.sent: list[int] = []

    def write(self, data: bytes) -> None:
        self.sent += list(data)

    def is_closing(self) -> bool:
        return False


async def test_an_xon_decided_before_a_newer_xoff_is_not_sent():
    fe = SerialFrontend(VirtualController(make_truth()))
    line = Line()
    fe._writer = line  # type: ignore[assignment]
    try:
        fe._xoff = False  # the buffer drained below the low mark: XON decided, sent next pass
        fe._spawn(fe._xon_later())
        fe._xoff = True  # held bytes refilled it past the high mark first: XOFF at once
        fe._put_flow(XOFF)
        for _ in range(3):
            await asyncio.sleep(0)
        assert line.sent == [XOFF]  # the sender stays held, as the control believes
        fe._xoff = False  # drained again: this XON is current and goes out
        fe._spawn(fe._xon_later())
        for _ in range(3):
            await asyncio.sleep(0)
        assert line.sent == [XOFF, XON]
    finally:
        fe._writer = None
        await fe.close()
