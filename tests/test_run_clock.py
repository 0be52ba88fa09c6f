"""One clock for a whole run: a re-probe round's touches and temperature
readings are stamped on the run's clock (contracts.jobs.RunClock: seconds since the run's first
program started), not from their own program's start, which put them at the start of the run
for the drift-aware estimate and the drift check. End to end over each real transport (a pty,
an asyncua server, a pymodbus server) against the simulated CNC, a chip forcing a re-probe of
one pose; the link is watched where the session reads it, and every journaled time is checked
against the monotonic instants between which its hit reached the session: no tolerance, no
timing assumption."""

from __future__ import annotations

import time
import warnings
from collections.abc import AsyncIterator
from typing import Any

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
from benchmarks.rigs.temperature_helpers import run_from_cnc
from benchmarks.rigs.warm_cnc import SPINDLE, machine_entry, write_config
from contracts.jobs import ProgramJob, RunClock
from contracts.messages import ProbeHit
from daemon.analysis.pipeline import hit_to_row
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.analysis.touch_centres import rows_to_centres
from daemon.config import load_daemon_config
from daemon.run.session import Session, State
from daemon.store.journal import Store
from drivers.hits import HitFactory
from simulators import thermal
from simulators.faults import Fault, FaultPlan
from tests.test_temperature_channels import cnc
from tests.test_temperature_reprobe import CHIP_AT, _seq

__all__ = ["cnc"]  # the warming CNC behind each transport (tests/test_temperature_channels.py)

EPS_S = 1e-6  # float rounding of the stored times, nothing else


class Watch:
    """The session's link with each program's call and each hit's arrival noted: the hit was
    stamped between ``before`` (the session asked for the next result) and ``after``."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, float]] = []  # (program run id, when handed to the link)
        self.arrivals: list[tuple[str, float, float]] = []  # (program, before, after)

    def attach(self, session: Any) -> None:
        run = session.link.run

        async def watched(job: ProgramJob) -> AsyncIterator[ProbeHit]:
            self.calls.append((job.run_id, time.monotonic()))
            agen = run(job)
            try:
                while True:
                    before = time.monotonic()
                    try:
                        hit = await anext(agen)
                    except StopAsyncIteration:
                        return
                    self.arrivals.append((job.run_id, before, time.monotonic()))
                    yield hit
            finally:
                await agen.aclose()

        session.link.run = watched


def _channels(transport: str, port: int) -> list[dict[str, Any]]:
    column = {"name": "column", "source": "transmitter", "address": "input:0", "scale": 0.1,
              "transmitter": {"host": "127.0.0.1", "port": port}}
    if transport.startswith("serial"):  # the DNC program prints the control's sensor
        return [{"name": "spindle", "address": thermal.FANUC_VARIABLE["Z"]}, column]
    return [{"name": "spindle", "source": "controller", **SPINDLE[transport]}, column]


@pytest.mark.asyncio
@pytest.mark.parametrize("cnc", ["serial-pty", "opcua", "modbus"], indirect=True)
async def test_a_re_probe_round_is_timed_on_the_runs_clock(cnc, tmp_path):
    rig, _, port = cnc
    rig.ctrl.dialect = "fanuc"
    pose = CHIP_AT[0]
    rig.ctrl.faults = FaultPlan([Fault(kind="chip", at_touch=_seq(*CHIP_AT), size_um=15.0)])
    entry = machine_entry(rig.link, _channels(rig.transport, port), {})
    watch = Watch()
    run = await run_from_cnc(load_daemon_config(write_config(tmp_path, entry)), rig.ctrl,
                             before=watch.attach)
    assert run.session.state == State.IDLE, run.session.reason
    (o,) = run.analysis.outliers  # the chip, repaired by the re-probe of its pose
    assert (o.pose, o.status, o.replaced_by_repeat) == (pose, "repaired", 100)
    store = Store(tmp_path / "journal.sqlite")
    try:
        hits = store.hits(run.run_id)  # as journaled, in the order they arrived
    finally:
        store.close()
    programs = [p for p, _ in watch.calls]
    assert programs == [run.run_id, f"{run.run_id}-rp1"]
    assert [p for p, _, _ in watch.arrivals] == [programs[0]] * 140 + [programs[1]] * 20
    assert len(hits) == 160 and {h.repeat for h in hits[140:]} == {100}
    t = [h.t_s for h in hits]
    # the first program's times are the link's own, from its program's start
    first_call = watch.calls[0][1]
    assert 0.0 < t[0] <= watch.arrivals[0][2] - first_call + EPS_S, t[0]
    # every hit on one clock: its time after the first hit's is what passed between them,
    # within the instants each reached the session (the re-probe round included)
    _, b0, a0 = watch.arrivals[0]
    for k, ((_, b, a), tk) in enumerate(zip(watch.arrivals, t, strict=True)):
        assert b - a0 - EPS_S <= tk - t[0] <= a - b0 + EPS_S, (k, tk, t[0], b - a0, a - b0)
    # the round's first touch comes after the plan's last, by the time that passed between them
    # (the faulty visit's screening and the round's program: it ran at ~0 s before the fix)
    last, first = 139, 140
    gap = t[first] - t[last]
    lo = watch.arrivals[first][1] - watch.arrivals[last][2]
    hi = watch.arrivals[first][2] - watch.arrivals[last][1]
    assert lo > 0.0 and lo - EPS_S <= gap <= hi + EPS_S, (t[last], t[first], lo, hi)
    assert t == sorted(t)
    # the centres the drift model and the drift check are handed: the re-probed visit last
    rows = [hit_to_row(run.run_id, h, run.session.setup.machine) for h in hits]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = rows_to_centres(rows, run.session.setup.artefact,
                               run.session.setup.plan.stylus_radius_mm)
    again = data.repeat >= 100
    assert again.sum() == 4 and set(data.centres.pose[again]) == {pose}
    assert data.centres.t_s[again].min() > data.centres.t_s[~again].max()
    # temperatures on the same clock: the start before the program at 0, the round's readings
    # after the plan's last touch (its polled pose read at its first touch), the run's end last
    readings = run.readings
    (run_end,) = [r for r in readings if r.channel == "column" and r.at == "end"]
    assert run_end.t_s >= t[-1] and all(0.0 <= r.t_s <= run_end.t_s for r in readings)
    start = [r for r in readings if r.at == "start" and r.reprobe_round == 0]
    assert len(start) == 2 and all(r.t_s <= t[0] for r in start), start
    assert [r.t_s for r in start if r.channel == "column"] == [0.0]
    plan_poses = [r for r in readings if r.at == "pose" and r.reprobe_round == 0]
    assert len(plan_poses) == 2 * 7 and all(r.t_s <= t[last] for r in plan_poses), plan_poses
    round_ = [r for r in readings if r.reprobe_round == 1]
    assert round_ and all(r.t_s >= t[last] for r in round_), round_
    (polled,) = [r for r in round_ if r.channel == "column"]
    assert (polled.at, polled.pose, polled.t_s) == ("pose", pose, t[first])
    # a printed channel: the plan program's end line taken as the round began, between them
    printed_end = [r for r in readings if r.channel == "spindle" and r.at == "end"
                   and r.reprobe_round == 0]
    if rig.transport.startswith("serial"):
        assert len(printed_end) == 1 and t[last] <= printed_end[0].t_s <= t[first], printed_end


def test_the_run_clock_starts_once_with_the_first_program():
    clock = RunClock()
    assert (clock.started, clock.t_s()) == (False, 0.0)  # the start sample, before the program
    first = ProgramJob("r", "", "fanuc", 2, clock=clock)
    second = ProgramJob("r-rp1", "", "fanuc", 1, clock=clock)
    a = HitFactory(first)
    origin = clock.origin
    assert origin is not None and a.program_start_s == 0.0
    hits_a = [a.make(n, {"X": 1.0}, True, f"a{n}") for n in (1, 2)]
    b = HitFactory(second)  # a later program: the origin stays the first's
    assert clock.origin == origin and b.program_start_s >= hits_a[-1].t_s
    (hit_b,) = [b.make(1, {"X": 1.0}, True, "b1")]
    assert 0.0 <= hits_a[0].t_s <= hits_a[1].t_s <= b.program_start_s <= hit_b.t_s
    # a job made on its own keeps its own clock (a program run outside a session)
    alone = HitFactory(ProgramJob("x", "", "fanuc", 1))
    assert alone.clock is not clock and alone.program_start_s == 0.0
    assert clock.start(origin + 5.0) >= 0.0 and clock.origin == origin


@pytest.mark.asyncio
async def test_a_link_stamping_nothing_is_stamped_on_the_runs_clock(tmp_path):
    """LinuxCNC's result lines carry no time: the session stamps them on the run's clock, from
    when it handed the program over (an unstarted clock would put every touch at 0)."""
    setup = thesis_setup()
    rows = thesis_rows(setup)
    store = Store(tmp_path / "j.sqlite")
    try:
        link = ReplayLink(rows, setup.machine)  # yields every hit with t_s 0
        s = Session(setup, link, store, tmp_path / "reports", prepare=prepare_from_rows(rows))
        watch = Watch()
        watch.attach(s)
        run_id = s.start("cli")
        await s.wait()
        assert s.state == State.IDLE, s.reason
        t = [h.t_s for h in store.hits(run_id)]
        assert len(t) == len(rows) and s.clock.started and link.jobs[0].clock is s.clock
        # stamped after each hit came out of the link, before the session asked for the next
        arrivals = watch.arrivals
        first_call = watch.calls[0][1]
        assert t[0] >= arrivals[0][2] - first_call - EPS_S and t[0] > 0.0
        for k in range(1, len(t) - 1):
            assert (arrivals[k][2] - arrivals[1][1] - EPS_S <= t[k] - t[0]
                    <= arrivals[k + 1][1] - arrivals[0][2] + EPS_S), k
    finally:
        store.close()
