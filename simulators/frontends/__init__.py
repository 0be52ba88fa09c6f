"""Controller-side protocol front-ends of the simulated CNC (serial DNC, OPC UA, Modbus, CAN)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterable


async def cancel_tasks(tasks: Iterable[asyncio.Task]) -> None:
    """Cancel a front-end's background tasks and wait for them; their own errors on the way
    out (a peer that vanished mid-write) do not stop the shutdown."""
    tasks = list(tasks)
    for t in tasks:
        t.cancel()
    for t in tasks:
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await t
