"""A cancellation that arrives together with a response is never lost (``keep_cancel``): every
request of the Modbus and OPC UA links is awaited through it."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable
from typing import TypeVar

T = TypeVar("T")


async def keep_cancel(request: Awaitable[T]) -> T:
    """``await request`` (a client library's request), raising the caller's cancellation if one
    arrived meanwhile. pymodbus waits for each response under ``asyncio.wait_for``, which in
    Python 3.11 returns the response instead of raising when it arrives in the same loop step
    as the cancellation (CPython gh-86296, fixed in 3.12): a poll loop then carried on polling
    and the daemon's stop never returned (one CI run, a Modbus controller). asyncua 2.1 waits
    with wait_for2, which raises there, but only on the paths that use it: the OPC UA link does
    not rest on that. A cancellation requested before the call (a task's cleanup after its own
    cancel) is not raised again."""
    task = asyncio.current_task()
    before = task.cancelling() if task is not None else 0
    result = await request
    if task is not None and task.cancelling() > before:
        raise asyncio.CancelledError
    return result
