"""The result-ring loop the OPC UA and Modbus gateway links share (drivers/result_ring.py),
driven through its primitive reads by a scripted ring: what ends a run, and with which words."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest

from contracts.jobs import ProgramJob
from contracts.messages import ProbeHit
from drivers.base import ControllerAborted, ControllerAlarm, LinkError
from drivers.modbus.link import ModbusLink
from drivers.opcua.link import OpcUaLink
from drivers.result_ring import Feed, ResultRingReader, RingPoll


def _hit(seq: int, triggered: bool = True) -> ProbeHit:
    return ProbeHit(seq=seq, pose=0, ball="B1", touch=seq, axes={"X": 1.0}, triggered=triggered,
                    t_s=0.0, raw=f"#{seq}", direction=(1.0, 0, 0), feed_mm_min=300.0, extra={})


class Scripted(ResultRingReader):
    """A ring whose polls are a script of (new results, state); results trigger unless their
    seq is in ``untriggered``; the feed is a script too."""

    ring_slots = 4

    def __init__(self, polls: list[tuple[int, str]], feeds: list[Feed] | None = None,
                 untriggered: frozenset[int] = frozenset()) -> None:
        self.polls, self.feeds, self.untriggered = list(polls), list(feeds or []), untriggered
        self.seq = 0
        self.acks: list[int] = []

    async def _poll_ring(self, job: ProgramJob, got: int) -> RingPoll:
        new, state = self.polls.pop(0)
        return RingPoll(new, state, "E-STOP")

    async def _read_results(self, new: int) -> AsyncIterator[ProbeHit]:
        for _ in range(new):
            self.seq += 1
            yield _hit(self.seq, self.seq not in self.untriggered)

    async def _acknowledge(self) -> None:
        self.acks.append(self.seq)

    async def _alarm_message(self, poll: RingPoll) -> str:
        return f"alarm {poll.alarm}"

    async def _feed(self, poll: RingPoll) -> Feed:
        return self.feeds.pop(0) if self.feeds else Feed.DONE

    def _result_timeout_s(self) -> float:
        return 3600.0

    def _timeout_message(self, poll: RingPoll, got: int, job: ProgramJob) -> str:
        return "timeout"

    async def _wait(self, progressed: bool) -> None:
        await asyncio.sleep(0)


def _run(ring: Scripted, touches: int) -> tuple[list[int], BaseException | None]:
    async def go() -> tuple[list[int], BaseException | None]:
        seen: list[int] = []
        try:
            async for hit in ring._ring_results(ProgramJob("r1", "", "fanuc", touches)):
                seen.append(hit.seq)
        except (LinkError, ControllerAlarm, ControllerAborted) as e:
            return seen, e
        return seen, None

    return asyncio.run(go())


def test_both_gateway_links_use_the_one_loop():
    for link in (OpcUaLink, ModbusLink):
        assert issubclass(link, ResultRingReader)
        assert "_ring_results" not in vars(link)


def test_every_result_in_order_acknowledged_per_batch_until_done():
    ring = Scripted([(0, "running"), (2, "running"), (1, "running"), (0, "done")])
    assert _run(ring, 3) == ([1, 2, 3], None)
    assert ring.acks == [2, 3]


def test_what_ends_a_run_and_its_words():
    seen, e = _run(Scripted([(5, "running")]), 10)
    assert seen == [] and str(e) == ("result ring overrun: 5 touches since the last read, "
                                     "ring holds 4")
    seen, e = _run(Scripted([(3, "running")], untriggered=frozenset({2})), 3)
    assert seen == [1, 2] and isinstance(e, ControllerAlarm)
    assert str(e) == "probe did not trigger at touch seq 2"
    seen, e = _run(Scripted([(1, "running"), (0, "alarm")]), 3)
    assert isinstance(e, ControllerAlarm) and str(e) == "alarm E-STOP"
    seen, e = _run(Scripted([(1, "hold"), (0, "idle")]), 3)
    assert isinstance(e, ControllerAborted)
    assert str(e) == "program reset on the controller after 1 of 3 touches"
    seen, e = _run(Scripted([(1, "running"), (0, "done")]), 3)
    assert isinstance(e, LinkError) and str(e) == "program ended with 1 of 3 touches"


def test_an_idle_program_before_it_ran_is_not_a_reset_and_feeding_comes_first():
    # idle before running (blocks still being streamed): fed, waited, then it runs and ends
    ring = Scripted([(0, "idle"), (0, "idle"), (0, "idle"), (1, "running"), (0, "done")],
                    feeds=[Feed.SENT, Feed.WAITING, Feed.AGAIN])
    assert _run(ring, 1) == ([1], None)
    assert ring.feeds == [] and ring.polls == []


@pytest.mark.parametrize("feed", [Feed.WAITING, Feed.SENT])
def test_a_done_state_is_not_judged_while_the_program_is_still_fed(feed):
    # the mailbox still holds blocks: "done" is not the end yet
    ring = Scripted([(0, "done"), (1, "running"), (0, "done")], feeds=[feed])
    assert _run(ring, 1) == ([1], None)
