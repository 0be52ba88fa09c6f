"""A temperature channel whose OPC UA node is misspelt in daemon.yaml: the first read at the
run's start finds no such node on the controller, says so once (a warning naming the channel,
the node and where to fix it), and the channel is not read again in that run — its pose and end
readings are journaled as not read with that reason, without a warning each (it warned 17 times
a run: at the start, every pose and the end)."""

from __future__ import annotations

import logging

import pytest

from benchmarks.rigs.rig_helpers import start_rig
from benchmarks.rigs.temperature_helpers import run_from_cnc
from benchmarks.rigs.warm_cnc import SPINDLE, machine_entry, warm_truth, write_config
from daemon.config import load_daemon_config
from daemon.run.session import State
from simulators.controller import VirtualController


@pytest.mark.asyncio
async def test_a_misspelt_node_is_said_once_per_run_and_not_read_again(tmp_path, caplog):
    rig = await start_rig("opcua", VirtualController(warm_truth()))
    try:
        channels = [{"name": "spindle", "source": "controller", **SPINDLE["opcua"]},
                    {"name": "spindel", "source": "controller",
                     "address": SPINDLE["opcua"]["address"].replace("Temperatures",
                                                                    "Temperatrues")}]
        cfg = load_daemon_config(write_config(tmp_path, machine_entry(rig.link, channels, {})))
        with caplog.at_level(logging.WARNING, logger="rumba.temperatures"):
            run = await run_from_cnc(cfg, rig.ctrl)
    finally:
        await rig.close()
    assert run.session.state == State.IDLE, run.session.reason
    said = [r.getMessage() for r in caplog.records if "spindel" in r.getMessage()]
    assert len(said) == 1, said
    assert "no such node on the controller (BadNodeIdUnknown)" in said[0]
    assert "not read again in this run (check the channel's address in daemon.yaml)" in said[0]
    mine = [r for r in run.readings if r.channel == "spindel"]
    assert [r.at for r in mine] == ["start", *["pose"] * 7, "end"]
    assert all(r.value_c is None and "no such node on the controller" in r.error
               for r in mine), mine
    assert all(r.error.startswith("not read: ") for r in mine[1:]), mine
    good = [r for r in run.readings if r.channel == "spindle"]
    assert len(good) == 9 and all(r.value_c is not None for r in good)
