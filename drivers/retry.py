"""Waiting and retrying for links: an event wait that never swallows a cancellation, and
exponential backoff that gives up at once on a refused first connection."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar

from drivers.base import LinkError

T = TypeVar("T")

REFUSED_HINT = ("nothing listens there: controller off, its server or interface not enabled, "
                "or a wrong host/port")


class Refused(LinkError):
    """The controller's host actively refused the connection (TCP RST, ECONNREFUSED): it is up
    and reachable, but nothing listens on that port. A link raises it from one attempt; a
    timeout or a protocol failure stays a plain ``LinkError``."""


def is_refused(e: BaseException) -> bool:
    return isinstance(e, Refused | ConnectionRefusedError)


async def wait_event(event: asyncio.Event, timeout_s: float | None) -> bool:
    """Wait for ``event`` up to ``timeout_s``; True if set. Unlike ``asyncio.wait_for`` on
    Python 3.11, a cancellation arriving together with the timeout is never swallowed."""
    waiter = asyncio.ensure_future(event.wait())
    try:
        done, _ = await asyncio.wait({waiter}, timeout=timeout_s)
    finally:
        waiter.cancel()
    return bool(done)


async def with_backoff(
    attempt: Callable[[], Awaitable[T]], *, what: str, timeout_s: float,
    first_delay_s: float = 0.25, max_delay_s: float = 5.0, refused_is_final: bool = False,
) -> T:
    """Retry ``attempt`` with exponential backoff until it succeeds or ``timeout_s`` passes.

    The last failure's message is kept so the operator sees why (refused, bad certificate …).
    ``refused_is_final``: a refused connection ends the wait at once (a first connection at
    start-up or in ``rumba verify``: waiting the whole timeout would not change the answer, and
    the operator should hear it now). Reconnections leave it False: a controller that reboots
    refuses for a while, then answers."""
    deadline = time.monotonic() + timeout_s
    delay = first_delay_s
    while True:
        try:
            return await attempt()
        except (TimeoutError, OSError, LinkError, ConnectionError) as e:
            if refused_is_final and is_refused(e):
                detail = f" ({e})" if str(e) else ""
                raise LinkError(f"{what}: connection refused{detail}: {REFUSED_HINT}") from None
            last = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
        left = deadline - time.monotonic()
        if left <= 0:
            raise LinkError(f"{what}: unreachable after {timeout_s:g} s ({last})")
        await asyncio.sleep(min(delay, left))
        delay = min(delay * 2, max_delay_s)
