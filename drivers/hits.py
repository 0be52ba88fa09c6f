"""Turning what a controller reports (seq + latched axes) into ``ProbeHit``s, for every link."""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import TypeVar

from contracts.jobs import ProgramJob
from contracts.messages import TOUCH_DIRECTIONS, ProbeHit
from drivers.base import LinkError

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


