"""A stop whose cancellation asyncio swallows still stops the run: Python 3.11's
``asyncio.wait_for`` returns a result that completed together with the cancel (gh-86296); a
SIGTERM on ``rumba verify`` landing just as a hit arrived let the run go on to DONE while verify
exited 143. Here the stop is timed deterministically into that window: the link schedules it
in the same loop step that hands the session its fifth hit."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
from contracts.jobs import ProgramJob
from contracts.messages import ProbeHit
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.run.session import Session, State
from daemon.store.journal import Store

STOP_AT = 5


class StopAsHitArrives(ReplayLink):
    """Calls ``stop`` (set by the test) right before it yields hit ``STOP_AT``: the stop's
    cancel reaches the session while ``wait_for`` holds that hit as its result."""

    stop: Callable[[], None] = staticmethod(lambda: None)

    async def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        async for hit in super().run(job):
            if hit.seq == STOP_AT:
                asyncio.get_running_loop().call_soon(self.stop)
            yield hit


@pytest.mark.parametrize("how", ["abort", "interrupt"])
async def test_a_stop_as_a_hit_arrives_still_stops_the_run(tmp_path, how):
    setup = thesis_setup()
    rows = thesis_rows(setup)
    store = Store(tmp_path / "j.sqlite")
    link = StopAsHitArrives(rows, setup.machine, delay_s=0.002)
    s = Session(setup, link, store, tmp_path / "reports", prepare=prepare_from_rows(rows))
    stops: list[asyncio.Task] = []
    stop = s.abort("hmi") if how == "abort" else s.interrupt("the daemon stopping")
    link.stop = lambda: stops.append(asyncio.ensure_future(stop))
    try:
        run_id = s.start("hmi")
        async with asyncio.timeout(30):
            await s.wait()
            assert stops and await stops[0]
        run = store.run(run_id)
        want = ("ABORTED", "aborted by hmi during CAPTURE") if how == "abort" else \
            ("INTERRUPTED", "interrupted by the daemon stopping during CAPTURE")
        assert (run.state, run.reason) == want and s.state == State(want[0]), run.reason
        # the hit in hand is journaled (nothing lost), then the run stops: the controller reset
        assert run.hits == STOP_AT and link.aborted == 1
    finally:
        store.close()
