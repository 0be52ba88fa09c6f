"""What the virtual CNC tells its front-ends: the event types and the stream that delivers them."""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass

from simulators.faults import Fault


@dataclass(frozen=True)
class PrintLine:
    text: str


@dataclass(frozen=True)
class TouchResult:
    slot: int  # (seq - 1) mod RING_SLOTS
    seq: int  # 1-based probing move number in the program
    values: dict[str, float]  # X Y Z (mm) and b c (deg), latched (end point on a miss)
    triggered: bool


@dataclass(frozen=True)
class StateChange:
    state: str
    alarm: str | None


@dataclass(frozen=True)
class Block:
    number: int  # 1-based line of the program


@dataclass(frozen=True)
class RequestRaised:
    """The start-of-shift macro asked for a run (a serial front-end prints its request line)."""

    machine: str


@dataclass(frozen=True)
class FaultEvent:
    kind: str
    fault: Fault


ControllerEvent = PrintLine | TouchResult | StateChange | Block | FaultEvent | RequestRaised


class EventStream:
    """One queue per subscriber. While a block runs (``hold``), its events wait for ``flush``:
    a result line appears when the probing move is over, not when it starts."""

    def __init__(self) -> None:
        self._subs: list[asyncio.Queue] = []
        self._deferring = False
        self._deferred: list[ControllerEvent] = []

    def subscribe(self) -> asyncio.Queue:
        q: asyncio.Queue = asyncio.Queue()
        self._subs.append(q)
        return q

    def unsubscribe(self, q: asyncio.Queue) -> None:
        with contextlib.suppress(ValueError):
            self._subs.remove(q)

    @property
    def has_subscribers(self) -> bool:
        return bool(self._subs)

    def hold(self) -> None:
        """Keep the events of the block about to run until its machine time has passed."""
        self._deferring = True

    def flush(self) -> None:
        """Deliver what was held and stop holding."""
        self._deferring = False
        events, self._deferred = self._deferred, []
        for ev in events:
            self.emit(ev)

    def emit(self, ev: ControllerEvent) -> None:
        if self._deferring:
            self._deferred.append(ev)
            return
        for q in self._subs:
            q.put_nowait(ev)
