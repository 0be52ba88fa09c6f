"""The controller's block look-ahead for streamed programs: a drip-fed control takes the next
block from its input only when fewer than N blocks wait for execution, which is what makes a DNC
receive buffer fill up and a Modbus mailbox wait."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from typing import Any

RUNNING = ("running", "hold")


class Lookahead:
    def __init__(self, controller: Any, blocks: int = 8) -> None:
        self.ctrl, self.blocks = controller, blocks
        self.fed = 0
        self.started = 0
        self._progress = asyncio.Event()

    def reset(self) -> None:
        self.fed = self.started = 0

    def on_event(self, ev: Any) -> None:
        """Feed every controller event here (Block numbers count executed blocks)."""
        kind = type(ev).__name__
        if kind == "Block":
            self.started = max(self.started, int(ev.number))
            self._progress.set()
        elif kind == "StateChange":
            self._progress.set()

    async def events(self) -> AsyncIterator[Any]:
        """The controller's events, each counted here before the front-end sees it."""
        q = self.ctrl.subscribe()
        while True:
            ev = await q.get()
            self.on_event(ev)
            yield ev

    async def feed(self, line: str, still: Callable[[], bool] | None = None) -> bool:
        """Wait for room in the look-ahead, then hand the block to the controller; with
        ``still``, only if it still holds after the wait (a RESET meanwhile drops the block
        instead of starting a new program with it). Return whether the block was fed."""
        while self.fed - self.started >= self.blocks and self.ctrl.state in RUNNING:
            self._progress.clear()
            await self._progress.wait()  # set by every Block and StateChange event
        if still is not None and not still():
            return False
        if self.ctrl.state not in RUNNING:
            self.reset()  # the first block of a stream starts a new program
        await self.ctrl.feed_block(line)
        self.fed += 1
        return True
