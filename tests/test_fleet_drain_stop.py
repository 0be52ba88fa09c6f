"""The drainer stops when told even if a wake-up arrives with the stop (Python 3.11's wait_for
loses such a cancellation, gh-86296): before the fix, daemon shutdown and the fleet benchmark's
daemons hung for ever in that case. No server needed: an empty outbox never connects."""

from __future__ import annotations

import asyncio

from daemon.store.drain import Drainer
from daemon.store.journal import Store


async def test_stop_is_not_lost_when_a_wake_arrives_with_it(tmp_path):
    for i in range(20):  # the race needs the wake in the same loop pass: vary the phase
        store = Store(tmp_path / f"j{i}.sqlite")
        d = Drainer(store, "postgresql://x@127.0.0.1:1/none")
        d.start()
        for _ in range(i % 4 + 1):
            await asyncio.sleep(0)
        d.wake.set()
        stop = asyncio.ensure_future(d.stop(flush_timeout_s=0.5))
        done, _ = await asyncio.wait({stop}, timeout=10)
        assert done, f"drainer did not stop (phase {i % 4 + 1})"
        store.close()
