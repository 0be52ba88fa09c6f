"""A temperature transmitter switched off but still routable (a defect once known): a
real TCP socket that accepts and never answers. The run does not wait for it at every pose: the
first read that gets no answer marks the channel unreachable for the run (journaled with the
reason at every pose), the pose reads run beside the capture, and the end tries it again."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest
import pytest_asyncio

from benchmarks.rigs.temperature_helpers import (
    SilentTransmitter,
    column,
    run_from_cnc,
    silent_transmitter,
)
from benchmarks.rigs.warm_cnc import SPINDLE, machine_entry, write_config
from contracts.temperatures import TemperatureChannel, TransmitterFile
from daemon.config import load_daemon_config
from daemon.run.session import State
from daemon.run.temperatures import TemperatureRecorder
from daemon.store.journal import Store
from daemon.store.temperatures import temperatures
from tests.test_temperature_channels import cnc

__all__ = ["cnc"]  # the warming CNC fixture, shared with the channels' end-to-end tests

UNREACHABLE = "not read again until the end of the run"


@pytest_asyncio.fixture
async def silent() -> AsyncIterator[tuple[SilentTransmitter, int]]:
    async with silent_transmitter() as served:
        yield served


@pytest.mark.asyncio
@pytest.mark.parametrize("cnc", ["opcua"], indirect=True)
async def test_a_silent_transmitter_is_asked_at_the_start_and_the_end_only(cnc, silent,
                                                                           tmp_path):
    rig, _, _ = cnc
    tx, port = silent
    channels = [{"name": "spindle", "source": "controller", **SPINDLE[rig.transport]},
                column(port)]
    cfg = load_daemon_config(write_config(tmp_path, machine_entry(rig.link, channels, {})))
    run = await run_from_cnc(cfg, rig.ctrl)
    assert run.session.state == State.IDLE, run.session.reason
    readings, analysis = run.readings, run.analysis
    col = [r for r in readings if r.channel == "column"]
    assert [(r.at, r.pose) for r in col] == [
        ("start", None), *[("pose", p) for p in range(7)], ("end", None)], col
    assert all(r.value_c is None for r in col)
    assert UNREACHABLE in col[0].error and "column" in col[0].error, col[0]
    for r in col[1:-1]:  # journaled at once, with the reason, nothing sent
        assert r.error.startswith("not read: unreachable since ") and " at start" in r.error
    assert UNREACHABLE not in col[-1].error and col[-1].error  # tried again, no answer
    assert (tx.connections, tx.requests) == (2, 2)  # the start and the end, not each pose
    spindle = [r for r in readings if r.channel == "spindle"]  # the other channel unaffected
    assert [r.at for r in spindle] == ["start", *["pose"] * 7, "end"]
    assert all(r.value_c is not None for r in spindle)
    assert analysis.temperatures["column"]["unread"] == 9
    assert UNREACHABLE in " ".join(analysis.temperatures["column"]["errors"])


@pytest.mark.asyncio
async def test_a_pose_read_runs_beside_the_capture(silent, tmp_path):
    """The transmitter answers the start, then falls silent: the pose's read is in flight when
    ``on_hit`` returns (nothing journaled for it yet), the next pose does not queue behind it,
    and the end waits for it (bounded) before trying the channel again."""
    tx, port = silent
    tx.answer_first = 1
    store = Store(tmp_path / "journal.sqlite")
    store.new_run("r1", "mill1", "test")
    ch = TemperatureChannel(name="column", source="transmitter", address="input:0", scale=0.1,
                            transmitter=TransmitterFile(host="127.0.0.1", port=port,
                                                        timeout_s=0.6))
    rec = TemperatureRecorder("mill1", (ch,), link=None, store=store,  # type: ignore[arg-type]
                              link_name="opcua")
    try:
        await rec.start("r1", 0.0)
        got = temperatures(store, "r1")
        assert [(r.at, r.value_c) for r in got] == [("start", pytest.approx(23.5))]
        tx.request_seen.clear()
        await rec.on_hit("r1", 0, 1.0)
        await asyncio.wait_for(tx.request_seen.wait(), 30)  # the request is out, unanswered
        assert len(temperatures(store, "r1")) == 1  # on_hit did not wait for its answer
        await rec.on_hit("r1", 0, 1.5)  # same pose: no second read
        await rec.on_hit("r1", 1, 2.0)
        got = temperatures(store, "r1")
        assert [(r.at, r.pose) for r in got[1:]] == [("pose", 1)]
        assert got[1].error == "not read: the previous read of this channel is still waiting"
        await rec.end("r1", 3.0)
        got = temperatures(store, "r1")
    finally:
        await rec.close()
        store.close()
    assert [(r.at, r.pose) for r in got] == [("start", None), ("pose", 1), ("pose", 0),
                                             ("end", None)]
    assert got[2].value_c is None and UNREACHABLE in got[2].error
    assert got[3].value_c is None and got[3].error
    # start and pose 0 on one connection, dropped after no answer; the end's retry on a new one
    assert (tx.connections, tx.requests) == (2, 3)
