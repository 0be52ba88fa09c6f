"""The operator panel's side of the CAN bus: buttons pressed by a test or an operator at the
terminal, lamps shown from the daemon's LAMP frames (frame map in contracts/can_frames.py)."""

from __future__ import annotations

import asyncio
import contextlib

import can

from contracts.can_frames import (
    LAMP_NAMES,
    OFFSET_LAMP,
    OFFSET_PANEL,
    PROGRESS_UNKNOWN,
    button_frame,
)
from simulators.frontends import cancel_tasks


class SimulatedPanel:
    def __init__(self, bus: can.BusABC, base_id: int = 0x640, heartbeat_s: float = 1.0) -> None:
        self.bus, self.base_id = bus, base_id
        self.lamp: str | None = None
        self.progress: int | None = None
        self.flags = 0
        self.history: list[str] = []  # lamp states in the order they were shown
        self.last_frame_at: float | None = None
        self._counter = 0
        self._changed = asyncio.Event()
        self._reader = can.AsyncBufferedReader()
        loop = asyncio.get_running_loop()
        self._notifier = can.Notifier(bus, [self._reader], timeout=0.05, loop=loop)
        self._tasks = [loop.create_task(self._lamps()), loop.create_task(self._alive(heartbeat_s))]

    def press(self, button: str, repeats: int = 1) -> None:
        """One press (sent ``repeats`` times with the same counter, as a bouncing contact)."""
        self._counter = (self._counter + 1) & 0xFF
        for _ in range(repeats):
            self.bus.send(button_frame(self.base_id, button, self._counter))

    async def wait_lamp(self, lamp: str, timeout: float = 5.0) -> None:
        async def seen() -> None:
            while self.lamp != lamp:
                self._changed.clear()
                await self._changed.wait()
        await asyncio.wait_for(seen(), timeout)

    async def _lamps(self) -> None:
        while True:
            msg = await self._reader.get_message()
            if msg.arbitration_id != self.base_id + OFFSET_LAMP or len(msg.data) < 4:
                continue
            self.last_frame_at = asyncio.get_running_loop().time()
            lamp = LAMP_NAMES.get(msg.data[0], f"unknown({msg.data[0]})")
            self.progress = None if msg.data[1] == PROGRESS_UNKNOWN else msg.data[1]
            self.flags = msg.data[2]
            if lamp != self.lamp:
                self.lamp = lamp
                self.history.append(lamp)
            self._changed.set()

    async def _alive(self, period_s: float) -> None:
        n = 0
        while True:
            n = (n + 1) & 0xFF
            with contextlib.suppress(can.CanError):
                self.bus.send(can.Message(arbitration_id=self.base_id + OFFSET_PANEL,
                                          is_extended_id=False, data=bytes([n])))
            await asyncio.sleep(period_s)

    async def close(self) -> None:
        await cancel_tasks(self._tasks)
        self._notifier.stop()
        self.bus.shutdown()
