"""The one loop that reads a run's results from a controller's result ring while its program
runs, shared by the links that poll one (OPC UA nodes, Modbus registers): python-can's
``BusABC`` pattern, the base does the loop and a link writes only its primitive reads.

Per pass the link polls the ring (``_poll_ring``: how many new results, the program state);
new results are read (``_read_results``), handed on one by one, a non-triggered touch stops the
run, and the link acknowledges the batch (``_acknowledge``). Without new results: a controller
alarm or a program reset on the control ends the run; the link may feed the program
(``_feed``: a block to stream); a finished program must have delivered every touch; no result
for ``result_timeout_s`` is a dead link; else the link waits (``_wait``) and polls again.
"""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from enum import Enum

from contracts.jobs import ProgramJob
from contracts.messages import ProbeHit
from drivers.base import ControllerAborted, ControllerAlarm, LinkError


@dataclass(frozen=True)
class RingPoll:
    """One poll of the ring: results the controller added since the last poll, and the state
    of the program there ("running", "hold", "idle", "done", "alarm", …)."""

    new: int
    state: str
    alarm: object = None  # what the controller says of its alarm (a text, a code)


class Feed(Enum):
    """What ``_feed`` did: sent a part of the program (progress: poll again at once), sent a
    command (poll again at once), waits for the controller to take what was sent (wait, then
    poll), or has nothing left to send (judge the program's end)."""

    SENT = "sent"
    AGAIN = "again"
    WAITING = "waiting"
    DONE = "done"


class ResultRingReader:
    """The polling loop over a controller's result ring; a link subclasses it and implements
    the primitive reads (and, if it streams its program, ``_feed``)."""

    ring_slots: int  # results the ring holds: more new ones at a poll is an overrun
    _progress_t: float  # when the controller last showed progress (a result, a block taken)
    overrun_since = "the last read"  # how the overrun message names the previous poll

    async def _poll_ring(self, job: ProgramJob, got: int) -> RingPoll:
        raise NotImplementedError

    def _read_results(self, new: int) -> AsyncIterator[ProbeHit]:
        """The ``new`` results after the last one read, in program order, each checked."""
        raise NotImplementedError

    async def _acknowledge(self) -> None:
        """Free the slots just read for the controller (no-op: the ring frees itself)."""

    async def _alarm_message(self, poll: RingPoll) -> str:
        raise NotImplementedError

    async def _feed(self, poll: RingPoll) -> Feed:
        """Send the controller what it needs next; a link that loaded its program has none."""
        return Feed.DONE

    def _timeout_message(self, poll: RingPoll, got: int, job: ProgramJob) -> str:
        raise NotImplementedError

    def _result_timeout_s(self) -> float:
        raise NotImplementedError

    async def _wait(self, progressed: bool) -> None:
        """Before the next poll (``progressed``: something happened since the last wait)."""
        raise NotImplementedError

    async def _ring_results(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        """The run's hits while the program runs, until it ends with every touch (or a
        ``LinkError`` / ``ControllerAlarm`` / ``ControllerAborted`` says why not)."""
        got = 0
        seen_running = False
        progressed = False
        self._progress_t = time.monotonic()
        while True:
            poll = await self._poll_ring(job, got)
            seen_running = seen_running or poll.state in ("running", "hold")
            if poll.new:
                if poll.new > self.ring_slots:
                    raise LinkError(f"result ring overrun: {poll.new} touches since "
                                    f"{self.overrun_since}, ring holds {self.ring_slots}")
                async for hit in self._read_results(poll.new):
                    got += 1
                    yield hit
                    if not hit.triggered:
                        raise ControllerAlarm(f"probe did not trigger at touch seq {hit.seq}")
                await self._acknowledge()
                self._progress_t = time.monotonic()  # the controller's silence counts from here
                progressed = True
                continue  # re-read: more may have arrived meanwhile
            if poll.state == "alarm":
                raise ControllerAlarm(await self._alarm_message(poll))
            if seen_running and poll.state == "idle":
                # Running, then idle without reaching the end: RESET on the control itself.
                raise ControllerAborted(f"program reset on the controller after {got} of "
                                        f"{job.touch_count} touches")
            feed = await self._feed(poll)
            if feed is Feed.SENT:
                self._progress_t = time.monotonic()
                progressed = True
                continue
            if feed is Feed.AGAIN:
                continue
            if feed is Feed.DONE:
                if poll.state == "done":
                    if got < job.touch_count:
                        raise LinkError(f"program ended with {got} of {job.touch_count} "
                                        "touches")
                    return
                if time.monotonic() - self._progress_t >= self._result_timeout_s():
                    raise LinkError(self._timeout_message(poll, got, job))
            await self._wait(progressed)
            progressed = False
