"""The program's result handshake as the simulated control runs it (``contracts.result_lines``
HANDSHAKE_VARIABLES): a program waits before a probing move while its ring of result slots is
full (counter - ack = ``RING_SLOTS``) and ends at the link's stop request.

At time scale 0 the program's own wait loop (a dwell and a re-read, in a loop) would spin the
event loop for as long as the link takes to read; so the front-end holds the control at the
counter write that fills the ring, and lets it go on once the link's ack (or stop) arrives — the
program then finds its ring free (or the stop) and goes on exactly as the loop would have. The
program text is unchanged: the loop and the stop check run as written.
"""

from __future__ import annotations

import asyncio
from typing import Any

from contracts.result_lines import HANDSHAKE_VARIABLES, RESULT_COUNTERS, RING_SLOTS


class RingPacer:
    """Listens to ``ctrl``'s variable writes (``VirtualController.variable_listeners``)."""

    def __init__(self, ctrl: Any, dialect: str) -> None:
        self.ctrl = ctrl
        self.counter_name = RESULT_COUNTERS[dialect]
        self.ack_name, self.stop_name = HANDSHAKE_VARIABLES[dialect]
        self.held = False  # the control waits for the link (the program's loop)
        self.holds = 0  # how often the ring was full (tests: the pacing happened)
        self._resume: asyncio.Task | None = None
        ctrl.variable_listeners.append(self._written)

    def close(self) -> None:
        if self._written in self.ctrl.variable_listeners:
            self.ctrl.variable_listeners.remove(self._written)

    def _value(self, name: str) -> float:
        v = self.ctrl.variables.get(name, 0.0)
        return float(v) if isinstance(v, int | float) else 0.0

    def full(self) -> bool:
        return self._value(self.counter_name) - self._value(self.ack_name) >= RING_SLOTS

    def _written(self, name: str, value: Any) -> None:
        if name == self.counter_name:
            if self.full() and self._value(self.stop_name) == 0 and \
                    self.ctrl.state == "running":
                self.ctrl.feed_hold()
                self.held = True
                self.holds += 1
        elif name in (self.ack_name, self.stop_name) and self.held and (
                not self.full() or self._value(self.stop_name) != 0):
            self.held = False
            if self.ctrl.state == "hold":
                self._resume = asyncio.get_running_loop().create_task(self.ctrl.start())
