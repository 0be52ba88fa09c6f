"""Waiting in tests for what a test waits for — a condition — never for time to pass."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable


async def until(cond: Callable[[], object], timeout_s: float = 30.0, what: str = "") -> None:
    """Poll ``cond`` until it holds; an ``AssertionError`` naming ``what`` after ``timeout_s``
    (a bound against a hang, far above the time a loaded machine needs)."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what or cond}")
        await asyncio.sleep(0.005)


async def settle(rounds: int = 20) -> None:
    """Let every task that is ready run (``rounds`` turns of the event loop, no clock): before
    checking that something did NOT happen in response to what is already queued."""
    for _ in range(rounds):
        await asyncio.sleep(0)
