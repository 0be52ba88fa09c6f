"""After a DNC program was stopped early, what the control still prints of it: plain DNC has no
remote reset, so the control executes the blocks it already holds (its receive buffer, its
look-ahead) and prints their result lines. The next tape waits until the last of those lines
came, or the control raised an alarm, or nothing came for ``result_timeout_s`` (a RESET there):
a line of the stopped program is never read as one of the next (its seq 1 lost, or a stale seq 1
taken for the new program's)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

log = logging.getLogger("rumba.serial")


async def drain_leftover(lines: asyncio.Queue, parse: Callable[[str], Any], after: int,
                         last: int, timeout_s: float) -> bool:
    """Read the stopped program's output from ``lines`` until its result line of seq ``last``
    (those after seq ``after`` may still come), an ``ALARM`` line or the connection's end;
    True then, False when nothing came for ``timeout_s`` (the control was reset, or it holds
    the program still)."""
    log.info("serial: the stopped program may still print touches %d-%d: the next tape waits "
             "for them", after + 1, last)
    while True:
        try:
            item = await asyncio.wait_for(lines.get(), timeout_s)
        except TimeoutError:
            log.warning("serial: no line from the stopped program for %g s (touches %d-%d not "
                        "printed): taken as reset at the control; the next tape goes",
                        timeout_s, after + 1, last)
            return False
        if isinstance(item, BaseException):
            return True  # the line closed: the next connect starts afresh
        if item.upper().startswith("ALARM"):
            log.info("serial: the stopped program ended in an alarm: %s", item)
            return True
        try:
            hit = parse(item)
        except ValueError:
            hit = None
        if hit is None:
            continue
        log.info("serial: result of the stopped program (not journaled): %s", item)
        if hit.seq >= last:
            return True
