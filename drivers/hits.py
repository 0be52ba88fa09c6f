"""Turning what a controller reports (seq + latched axes) into ``ProbeHit``s, for every link."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import replace
from typing import TypeVar

from daemon.messages import TOUCH_DIRECTIONS, ProbeHit
from drivers.base import LinkError, ProgramJob

T = TypeVar("T")

MAX_LINEAR_MM = 1e5
"""Largest plausible latched linear position: no machine tool travels 100 m, so a larger value
is a corrupted record, not a measurement (a garbage int32 in 0.1 µm reaches 214 748 mm)."""
MAX_ROTARY_DEG = 1e5
"""Largest plausible latched rotary position (a multi-turn axis stays far below)."""


class MalformedResult(LinkError):
    """A result record from the controller failed validation; the message names the record,
    the field, the value found and what was expected. Never retried: the data are unusable."""


def check_axes(axes: dict[str, float], where: str) -> None:
    """Raise ``MalformedResult`` unless every latched position is finite and plausible."""
    for key, value in axes.items():
        limit = MAX_LINEAR_MM if key in ("X", "Y", "Z") else MAX_ROTARY_DEG
        unit = "mm" if key in ("X", "Y", "Z") else "deg"
        if not math.isfinite(value) or abs(value) > limit:
            raise MalformedResult(f"malformed result ({where}): {key} = {value!r} {unit}, "
                                  f"expected a finite value within ±{limit:g} {unit}")


class HitFactory:
    """Names a result by its sequence number using the job's touch table (``job.touches``).

    ``make`` also checks what every record-based link (OPC UA, Modbus) must deliver: results in
    program order (the n-th result is touch seq n), within the program, with plausible
    positions; anything else raises ``MalformedResult`` at once instead of being journaled."""

    def __init__(self, job: ProgramJob) -> None:
        self.job = job
        self.t0 = time.monotonic()
        self._by_seq = {t.seq: t for t in job.touches}
        self.made = 0

    def t_s(self) -> float:
        return time.monotonic() - self.t0

    def make(self, seq: int, axes: dict[str, float], triggered: bool, raw: str,
             where: str = "") -> ProbeHit:
        where = where or raw
        expected = self.made + 1
        if seq != expected:
            raise MalformedResult(f"malformed result ({where}): touch seq {seq}, expected "
                                  f"{expected} (results arrive in program order)")
        tid = self._by_seq.get(seq)
        total = len(self._by_seq) or self.job.touch_count
        if (self._by_seq and tid is None) or (total and seq > total):
            raise MalformedResult(f"controller reported touch seq {seq}, not in the program "
                                  f"(1..{total})")
        check_axes(axes, where)
        self.made = expected
        return ProbeHit(
            seq=seq, pose=tid.pose if tid else -1, ball=tid.ball if tid else "",
            touch=tid.touch if tid else 0, repeat=tid.repeat if tid else 0,
            axes=axes, triggered=triggered, t_s=self.t_s(), raw=raw,
            direction=TOUCH_DIRECTIONS.get(tid.touch, (0.0, 0.0, 0.0)) if tid else (0.0, 0.0, 0.0),
        )

    def complete(self, hit: ProbeHit, raw: str) -> ProbeHit:
        """Fill what a dialect's line parser could not know (time, raw line, pose/ball/touch)."""
        check_axes(hit.axes, f"result line {raw.strip()[:80]!r}")  # 400 digits parse as inf
        tid = self._by_seq.get(hit.seq)
        changes: dict = {"t_s": self.t_s(), "raw": hit.raw or raw}
        if tid is not None and not hit.ball:
            changes.update(pose=tid.pose, ball=tid.ball, touch=tid.touch, repeat=tid.repeat)
        return replace(hit, **changes)


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
    first_delay_s: float = 0.25, max_delay_s: float = 5.0,
) -> T:
    """Retry ``attempt`` with exponential backoff until it succeeds or ``timeout_s`` passes.

    The last failure's message is kept so the operator sees why (refused, bad certificate …)."""
    deadline = time.monotonic() + timeout_s
    delay = first_delay_s
    while True:
        try:
            return await attempt()
        except (TimeoutError, OSError, LinkError, ConnectionError) as e:
            last = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
        left = deadline - time.monotonic()
        if left <= 0:
            raise LinkError(f"{what}: unreachable after {timeout_s:g} s ({last})")
        await asyncio.sleep(min(delay, left))
        delay = min(delay * 2, max_delay_s)
