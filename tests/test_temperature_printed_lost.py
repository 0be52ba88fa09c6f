"""A temperature line the DNC program should have printed but that never came (a
review of the Sinumerik WRITE path): Siemens documents that WRITE refuses a line once its file
outgrows MD11420 $MN_LEN_PROTOCOL_FILE ("the block or data is not saved"), and the DNC reader
drops a garbled or out-of-range line. The missing reading is journaled as not read with the
reason, the summary says the start was not read, and the change limit is not passed on a span
that lacks it. End to end over a real pty against the simulated 840D, whose first WRITE is
lost (the simulator's drop_result_line fault)."""

from __future__ import annotations

import pytest

from benchmarks.rigs.temperature_helpers import run_from_cnc
from benchmarks.rigs.warm_cnc import machine_entry, write_config
from daemon.config import load_daemon_config
from daemon.run.session import State
from daemon.run.temperatures import NOT_PRINTED
from simulators import thermal
from simulators.faults import Fault, FaultPlan
from tests.test_temperature_channels import cnc

__all__ = ["cnc"]  # the warming CNC fixture, shared with the channels' end-to-end tests


@pytest.mark.asyncio
@pytest.mark.parametrize("cnc", ["serial-pty"], indirect=True)
async def test_a_start_line_that_never_came_is_journaled_with_the_reason(cnc, tmp_path):
    rig, _, _ = cnc
    rig.ctrl.dialect = "siemens"
    # the control loses the program's first WRITE (the RTEMP S line), nothing else
    rig.ctrl.faults = FaultPlan([Fault(kind="drop_result_line", at_block=1)])
    entry = machine_entry(rig.link, [{"name": "spindle",
                                      "address": thermal.SIEMENS_VARIABLE["Z"]}],
                          {"spindle": {"change_c": 50.0}})
    entry["dialect"] = "siemens"
    run = await run_from_cnc(load_daemon_config(write_config(tmp_path, entry)), rig.ctrl)
    assert run.session.state == State.IDLE, run.session.reason
    assert not any(line.startswith("RTEMP S ") for line in rig.ctrl.printed)  # it was lost
    got = {(r.at, r.pose): r for r in run.readings}
    assert sorted(got, key=str) == sorted([("start", None), *[("pose", p) for p in range(7)],
                                           ("end", None)], key=str)
    start = got[("start", None)]
    assert start.value_c is None
    assert start.error == NOT_PRINTED.format(where="the start"), start
    assert all(got[("pose", p)].value_c is not None for p in range(7))
    assert got[("end", None)].value_c is not None
    t = run.analysis.temperatures["spindle"]
    assert (t["start_c"], t["unread"], t["first_at"]) == (None, 1, "pose 0")
    assert NOT_PRINTED.format(where="the start") in t["errors"]
    assert run.verdict["status"] == "WARN", run.verdict
    assert any("not checked over the whole run" in r and "pose 0 → end" in r
               for r in run.verdict["reasons"]), run.verdict["reasons"]
