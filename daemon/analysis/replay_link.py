"""A CNC link that replays probing-log rows as ProbeHits: the daemon's run without a controller.

It stands in for a controller in-process (the state machine's tests, the daemon's benchmarks,
a dry run of a recorded log); the real transports and the simulator are exercised by the
end-to-end suite. Faults are switched by touch sequence number.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass, field, replace

from contracts.jobs import ProgramJob, Verdict
from contracts.messages import ProbeHit, TouchId
from contracts.probing_log import LogRow
from contracts.touch_table import TouchInfo, TouchTable
from daemon.analysis.pipeline import Prepared, row_to_hit
from drivers.base import Capabilities, CncLink, ControllerAlarm, LinkError, StartRequest
from identification.kinematics import Machine


@dataclass
class Faults:
    no_trigger_at: int | None = None  # this seq latches nothing (ball missing)
    link_error_at: int | None = None  # connection lost before this seq
    hang_at: int | None = None  # controller goes silent before this seq (feed hold)
    wrong_identity_at: int | None = None  # this seq is reported as another ball
    stop_after: int | None = None  # program ends early after this many touches


CAPS = Capabilities(start_request=True, loads_program=True)


@dataclass
class ReplayLink(CncLink):
    rows: Sequence[LogRow]
    machine: Machine
    delay_s: float = 0.0
    faults: Faults = field(default_factory=Faults)
    capabilities: Capabilities = CAPS
    verdicts: list[Verdict] = field(default_factory=list)
    aborted: int = 0
    connects: int = 0
    closed: int = 0
    jobs: list[ProgramJob] = field(default_factory=list)
    request: asyncio.Event = field(default_factory=asyncio.Event)

    async def connect(self) -> None:
        self.connects += 1

    async def wait_start_request(self) -> StartRequest:
        await self.request.wait()
        self.request.clear()
        return StartRequest("cnc", detail="start of shift")

    async def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        self.jobs.append(job)
        f = self.faults
        for row in self.rows:
            if f.stop_after is not None and row.seq > f.stop_after:
                return
            if row.seq == f.link_error_at:
                raise LinkError("connection reset by controller")
            if row.seq == f.hang_at:
                await asyncio.sleep(3600)
            await asyncio.sleep(self.delay_s)
            hit = row_to_hit(row, self.machine)
            hit = replace(hit, t_s=0.0, raw=f"replay {row.seq}")
            if row.seq == f.wrong_identity_at:
                hit = replace(hit, ball="XX")
            if row.seq == f.no_trigger_at:
                yield replace(hit, triggered=False)
                raise ControllerAlarm(f"probe did not trigger (seq {row.seq})")
            yield hit

    async def write_verdict(self, verdict: Verdict) -> None:
        self.verdicts.append(verdict)

    async def abort(self) -> None:
        self.aborted += 1

    async def close(self) -> None:
        self.closed += 1


def prepare_from_rows(rows: Sequence[LogRow]):
    """A ``Session(prepare=…)`` building the job's touch table from the log rows."""

    def prepare(setup, run_id: str, last_good=None) -> Prepared:
        touches = TouchTable(TouchInfo(TouchId(r.seq, r.pose, r.ball, r.touch, r.repeat),
                                       r.b_cmd_deg, r.c_cmd_deg, (r.dir_x, r.dir_y, r.dir_z),
                                       r.feed_mm_min) for r in rows)
        job = ProgramJob(run_id, "(replayed log)", setup.dialect, len(touches), touches=touches)
        return Prepared(job, estimated_s=4.0 * len(touches))

    return prepare
