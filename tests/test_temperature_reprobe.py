"""Temperatures of a re-probe round over plain DNC: the re-probe program
(daemon/run/reprobe.py) prints its own RTEMP start, pose and end lines, its poses numbered by
its own plan. Each reading is journaled under the plan pose actually re-probed and marked with
its round; the run's start stays the plan program's start and its end is the last program's
end. End to end over a real pty against the simulated Fanuc, a chip on one ball forcing the
re-probe, a printed channel and a polled transmitter beside it; the one simulated machine keeps
warming through the round (simulators/thermal.py: its clock runs on across programs)."""

from __future__ import annotations

import pytest

from benchmarks.rigs.daemon_helpers import thesis_setup
from benchmarks.rigs.temperature_helpers import run_from_cnc
from benchmarks.rigs.warm_cnc import machine_entry, sensor, write_config
from daemon.analysis.pipeline import prepare
from daemon.config import load_daemon_config
from daemon.run.session import State
from simulators import thermal
from simulators.faults import Fault, FaultPlan
from tests.test_temperature_channels import cnc

__all__ = ["cnc"]  # the warming CNC fixture, shared with the channels' end-to-end tests

CHIP_AT = (3, "B2", 2)  # pose, ball, touch: pose 3 is probed again, all four balls


def _seq(pose: int, ball: str, touch: int) -> int:
    job = prepare(thesis_setup(), "probe").job  # the plan of machine_entry (thesis_ch3_7poses)
    return next(t.id.seq for t in job.touches
                if (t.id.pose, t.id.ball, t.id.touch) == (pose, ball, touch))


def _where(rs: list) -> list[tuple[str, int | None, int]]:
    # getattr: the readings of a rumba that did not tell the rounds apart compare as round 0
    return [(r.at, r.pose, getattr(r, "reprobe_round", 0)) for r in rs]


@pytest.mark.asyncio
@pytest.mark.parametrize("cnc", ["serial-pty"], indirect=True)
async def test_a_re_probe_rounds_temperatures_belong_to_the_pose_it_probes_again(cnc, tmp_path):
    rig, _, port = cnc
    rig.ctrl.dialect = "fanuc"
    pose = CHIP_AT[0]
    rig.ctrl.faults = FaultPlan([Fault(kind="chip", at_touch=_seq(*CHIP_AT), size_um=15.0)])
    channels = [{"name": "spindle", "address": thermal.FANUC_VARIABLE["Z"]},
                {"name": "column", "source": "transmitter", "address": "input:0",
                 "scale": 0.1, "transmitter": {"host": "127.0.0.1", "port": port}}]
    entry = machine_entry(rig.link, channels, {"spindle": {"change_c": 50.0}})
    run = await run_from_cnc(load_daemon_config(write_config(tmp_path, entry)), rig.ctrl)
    assert run.session.state == State.IDLE, run.session.reason
    (o,) = run.analysis.outliers  # the chip, repaired by the re-probe of its pose
    assert (o.pose, o.ball, o.status, o.replaced_by_repeat) == (pose, "B2", "repaired", 100)
    assert run.session.done == 140 + 20
    spindle = [r for r in run.readings if r.channel == "spindle"]
    assert _where(spindle) == [
        ("start", None, 0), *[("pose", p, 0) for p in range(7)], ("end", None, 0),
        ("start", None, 1), ("pose", pose, 1), ("end", None, 1)], spindle
    values = [r.value_c for r in spindle]
    # the machine keeps warming through the round (one simulated machine, its clock running on
    # across the two programs): the round starts where the plan's program ended, not cold
    assert None not in values and values == sorted(values), values
    assert values[9] >= values[8] > values[0] + 1.0, values  # 8 °C rise, τ 5 min
    lo, hi = sensor("Z", 0.0), sensor("Z", 1e9)  # each on the warm-up curve
    assert all(lo - 5e-4 <= v <= hi + 5e-4 for v in values), values
    # no reading is warmer than the machine once everything ran
    assert values[-1] <= sensor("Z", rig.ctrl.thermal_time_s) + 5e-4, values
    # a polled channel: the round's pose read at the plan pose, the run's end after it
    column = [r for r in run.readings if r.channel == "column"]
    assert _where(column) == [("start", None, 0), *[("pose", p, 0) for p in range(7)],
                              ("pose", pose, 1), ("end", None, 0)], column
    polled = [r.value_c for r in column]  # read in this order: warming on through the round
    assert None not in polled and polled == sorted(polled), polled
    assert polled[-1] <= round(sensor("X", rig.ctrl.thermal_time_s) / 0.1) * 0.1 + 1e-9, polled
    # the run's start is the plan program's, its end the last program's: the whole run
    t = run.analysis.temperatures["spindle"]
    assert (t["start_c"], t["end_c"]) == (values[0], values[-1])
    assert t["change_over"] == "start → end" and t["change_c"] == pytest.approx(
        values[-1] - values[0])
    assert [(p["pose"], p["reprobe_round"]) for p in t["per_pose"]] == [
        *[(p, 0) for p in range(7)], (pose, 1)]
    assert t["unread"] == 0
    assert not any("temperature change spindle" in r for r in run.verdict["reasons"])
    assert run.report is not None
    page = run.report[0].read_text(encoding="utf-8")
    assert f"{pose}: {values[10]:.1f} (re-probe 1)" in page  # the round's pose reading
