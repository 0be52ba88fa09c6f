"""Turning what a controller reports (seq + latched axes) into ``ProbeHit``s, for every link."""

from __future__ import annotations

import math

from contracts.jobs import ProgramJob
from contracts.messages import ProbeHit
from contracts.result_lines import MAX_RESULT_DEG, MAX_RESULT_MM
from drivers.base import LinkError


class MalformedResult(LinkError):
    """A result record from the controller failed validation; the message names the record,
    the field, the value found and what was expected. Never retried: the data are unusable."""


def check_axes(axes: dict[str, float], where: str) -> None:
    """Raise ``MalformedResult`` unless every latched position is finite and plausible (the
    limits of a printed result line: a garbage int32 in 0.1 µm reaches 214 748 mm)."""
    for key, value in axes.items():
        limit = MAX_RESULT_MM if key in ("X", "Y", "Z") else MAX_RESULT_DEG
        unit = "mm" if key in ("X", "Y", "Z") else "deg"
        if not math.isfinite(value) or abs(value) > limit:
            raise MalformedResult(f"malformed result ({where}): {key} = {value!r} {unit}, "
                                  f"expected a finite value within ±{limit:g} {unit}")


class HitFactory:
    """Checks what a controller reports and names it through the job's touch table
    (``job.touches``, the one place a touch is identified).

    ``make`` also checks what every record-based link (OPC UA, Modbus) must deliver: results in
    program order (the n-th result is touch seq n), within the program, with plausible
    positions; anything else raises ``MalformedResult`` at once instead of being journaled."""

    def __init__(self, job: ProgramJob) -> None:
        self.job = job
        # made as the link starts the program: it starts the run's clock (the first program's
        # start is the run's origin) and every hit is stamped on it, a re-probe round's too
        # (contracts.jobs.RunClock; each program's own origin put a round at the run's start)
        self.clock = job.clock
        self.program_start_s = self.clock.start()  # this program's start on the run clock
        self.made = 0

    def t_s(self) -> float:
        """When the result reached the daemon, on the run clock. Never the controller's own
        clock: a control's cycle timer (the simulator's published machine time) restarts with
        every program and runs on another oscillator; a link that ever reads it must place it
        at ``program_start_s`` + that time, or a re-probe round lands at the run's start."""
        return self.clock.t_s()

    def make(self, seq: int, axes: dict[str, float], triggered: bool, raw: str,
             where: str = "") -> ProbeHit:
        where = where or raw
        expected = self.made + 1
        if seq != expected:
            raise MalformedResult(f"malformed result ({where}): touch seq {seq}, expected "
                                  f"{expected} (results arrive in program order)")
        table = self.job.touches
        total = len(table) or self.job.touch_count
        if (table and seq not in table) or (total and seq > total):
            raise MalformedResult(f"controller reported touch seq {seq}, not in the program "
                                  f"(1..{total})")
        check_axes(axes, where)
        self.made = expected
        return table.named(seq, axes, triggered, t_s=self.t_s(), raw=raw)

    def complete(self, hit: ProbeHit, raw: str) -> ProbeHit:
        """A hit decoded by the dialect's line parser, checked, with time and raw line set and
        what the line could not say filled from the touch table."""
        check_axes(hit.axes, f"result line {raw.strip()[:80]!r}")  # 400 digits parse as inf
        return self.job.touches.fill(hit, t_s=self.t_s(), raw=hit.raw or raw)
