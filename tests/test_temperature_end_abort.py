"""A run stopped while it waits in ``TemperatureRecorder.end`` for its last reads (the program
has finished): every read it waits for — the last pose's, still in flight, or an end read — is
journaled exactly once, with the value that came, or ``STOPPED``; never zero rows, never two.
The session's order: the run is cancelled (an abort from the HMI, the CAN panel, a signal, the
CNC), then, unwound, its ending stops the recorder (``daemon/run/ending.py``)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

import pytest
import pytest_asyncio

from benchmarks.rigs.temperature_helpers import one_channel_recorder
from contracts.temperatures import TemperatureChannel
from daemon.run.temperatures import STOPPED, TemperatureRecorder
from daemon.store.journal import Store
from daemon.store.temperatures import temperatures
from tests.test_temperature_abort import running_reads

VALUE_C = 24.25


class GatedLink:
    """A link whose temperature reads answer when the test says so; counts the reads asked."""

    def __init__(self) -> None:
        self.release = asyncio.Event()
        self.asked = 0
        self.answered = False

    async def read_temperature(self, ch: TemperatureChannel) -> float:
        self.asked += 1
        await self.release.wait()
        self.answered = True  # the read's task completes in this same step
        return VALUE_C


@pytest_asyncio.fixture
async def gated(tmp_path) -> AsyncIterator[tuple[Store, GatedLink, TemperatureRecorder]]:
    """Run r1's recorder of one OPC UA channel read through a ``GatedLink``, on a real journal."""
    link = GatedLink()
    async with one_channel_recorder(tmp_path / "journal.sqlite", link) as (store, rec):
        yield store, link, rec


async def next_step() -> None:
    """One turn of the event loop: the callbacks ready now run before the test goes on."""
    await asyncio.sleep(0)


@pytest.mark.asyncio
@pytest.mark.parametrize("read", ["pose", "end"])
@pytest.mark.parametrize("when", ["not started", "waiting", "answered"])
async def test_an_abort_while_the_run_waits_for_its_last_reads_journals_each_read_once(
        gated, read, when):
    """``read`` "pose": the last touch's hit started pose 6's read and the run went straight
    into ``end``, which waits for it; "end": no pose read left, ``end`` waits for its own
    sample. The abort comes before the read ever ran, while it waits for its answer, or in the
    same instant as the answer (a value that came is journaled, not cut)."""
    store, link, rec = gated

    async def run() -> None:  # the session's run task from its last hit on, and its ending
        try:
            if read == "pose":
                await rec.on_hit("r1", 6, 9.0)  # no yield: end() is reached before it runs
            await rec.end("r1", 9.5)
        except asyncio.CancelledError:
            await rec.stop("r1")
            raise

    task = asyncio.create_task(run())
    await next_step()  # the run is in end(), waiting; the read created, not yet run
    if when != "not started":
        while not link.asked:
            await next_step()
    if when == "answered":
        link.release.set()
        while not link.answered:
            await next_step()
    assert not task.done() and temperatures(store, "r1") == []
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    assert task.cancelled()
    got = [(r.channel, r.at, r.pose, r.value_c, r.error) for r in temperatures(store, "r1")]
    at, pose = ("pose", 6) if read == "pose" else ("end", None)
    assert got == [("spindle", at, pose, *((VALUE_C, "") if when == "answered"
                                          else (None, STOPPED)))], got
    assert running_reads() == []  # no read of the run outlives it
    if when != "not started":  # (not started: the read may still begin before the stop)
        assert link.asked == 1  # nothing asked again after the stop
