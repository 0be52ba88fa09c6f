"""Modbus TCP: our pymodbus client against the simulator's pymodbus server (real TCP, free
loopback port), the register map's encodings, and mbpoll as an independent peer."""

from __future__ import annotations

import asyncio
import re
import shutil

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymodbus.client import AsyncModbusTcpClient

from drivers.base import LinkError, Verdict
from drivers.link_config import ModbusLinkConfig
from drivers.modbus import ModbusLink, program_blocks
from drivers.modbus_map import (
    LINEAR_COUNTS_PER_MM,
    MAP_ID,
    addr,
    decode_slot,
    encode_slot,
    i32_words,
    slot_address,
    text_words,
    words_i32,
    words_text,
)
from simulators.controller import VirtualController
from simulators.frontends.modbus import ModbusFrontend
from tests.transport_sim import (
    first_touch_of,
    hits_until_miss,
    latched_equal,
    make_job,
    make_truth,
    real_setup,
)

DIALECT = "fanuc"


@pytest.fixture
async def sim():
    ctrl = VirtualController(make_truth(), dialect=DIALECT)
    fe = ModbusFrontend(ctrl)
    port = await fe.start()
    link = ModbusLink(ModbusLinkConfig(transport="modbus", port=port, connect_timeout_s=2))
    yield ctrl, fe, port, link
    await link.close()
    await fe.stop()


async def until(pred, timeout: float = 5.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not pred():
        assert loop.time() < end, "condition not reached"
        await asyncio.sleep(0.01)


async def test_start_of_shift_cycle_streams_blocks_and_writes_verdict(sim):
    ctrl, fe, _, link = sim
    await link.connect()
    ctrl.raise_start_request()
    await asyncio.wait_for(link.wait_start_request(), 5)
    await until(lambda: ctrl.busy)
    job = make_job(ctrl.truth, DIALECT)  # 20 touches > 16 slots
    hits = [h async for h in link.run(job)]
    await link.write_verdict(Verdict("FAIL", "r"))
    await until(lambda: ctrl.done and not ctrl.busy and ctrl.verdict == 3)
    latched_equal(hits, ctrl, job, tol_mm=0.5 / LINEAR_COUNTS_PER_MM + 1e-9)  # 0.1 µm counts
    # every block crossed the mailbox intact and in order ('%' framing is not streamed)
    assert fe.blocks_taken == len(program_blocks(job.text)) and fe.alarms == []
    # the CNC dropped its request: the next wait clears DONE and waits for a fresh request
    ctrl.request = False
    waiter = asyncio.create_task(link.wait_start_request())
    await until(lambda: not ctrl.done)
    assert not waiter.done()
    waiter.cancel()


async def test_probe_miss_yields_hit_then_alarm_with_text():
    ctrl, job = real_setup(DIALECT, errors={"absent_balls": ["B1"]})
    miss = first_touch_of(job, "B1")
    fe = ModbusFrontend(ctrl)
    link = ModbusLink(ModbusLinkConfig(transport="modbus", port=await fe.start()))
    await link.connect()
    try:
        await hits_until_miss(link, job, miss)
        # the link stopped streaming at the miss; ABORT resets the starving control
        assert ctrl.state == "running"
        await link.abort()
        await until(lambda: ctrl.state == "idle" and fe.regs[addr("STATE")] == 0)
    finally:
        await link.close()
        await fe.stop()


async def test_cnc_registers_are_read_only_and_sequence_errors_alarm(sim):
    ctrl, fe, port, _ = sim
    client = AsyncModbusTcpClient("127.0.0.1", port=port)
    await client.connect()
    try:
        rr = await client.write_registers(addr("STATE"), [4], device_id=1)
        assert rr.isError()  # exception 02: CNC-owned register
        rr = await client.write_registers(addr("MBX_LEN"), [5, *text_words("G0 X1", 3)],
                                          device_id=1)
        assert not rr.isError()
        await client.write_registers(addr("MBX_SEQ"), [7], device_id=1)  # expected 1
        await client.write_registers(addr("MBX_READY"), [1], device_id=1)
        await until(lambda: fe.regs[addr("STATE")] == 3)
        rr = await client.read_holding_registers(addr("ALARM_CODE"), count=1, device_id=1)
        assert rr.registers == [2]
        text = await client.read_holding_registers(addr("ALARM_TEXT"), count=32, device_id=1)
        assert "sequence" in words_text(text.registers)
        assert fe.blocks_taken == 0 and ctrl.touches == []
    finally:
        client.close()


async def test_wrong_base_address_is_one_clear_error(sim):
    _, _, port, _ = sim
    link = ModbusLink(ModbusLinkConfig(transport="modbus", port=port, base_address=100,
                                       connect_timeout_s=1))
    with pytest.raises(LinkError, match="expected the rumba map"):
        await link.connect()
    await link.close()


async def test_unreachable_controller_is_one_clear_error():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    link = ModbusLink(ModbusLinkConfig(transport="modbus", port=port, connect_timeout_s=0.5))
    with pytest.raises(LinkError, match="unreachable"):
        await link.connect()


def test_block_too_long_is_refused_with_its_line():
    with pytest.raises(LinkError, match="line 2"):
        program_blocks("G0 X1\n(" + "A" * 200 + ")")


@given(st.floats(-200000, 200000, allow_nan=False), st.floats(-2000, 2000, allow_nan=False),
       st.integers(1, 2**32 - 1), st.booleans())
def test_slot_round_trip_to_register_resolution(x_mm, c_deg, seq, trig):
    values = {"X": x_mm, "Y": -x_mm / 3, "Z": 0.0, "b": c_deg / 2, "c": c_deg,
              "triggered": float(trig)}
    regs = encode_slot(seq, values)
    assert len(regs) == 16 and all(0 <= r <= 0xFFFF for r in regs)
    s, axes, t = decode_slot(regs)
    assert (s, t) == (seq, trig)
    assert axes["X"] == pytest.approx(x_mm, abs=0.5e-4 + 1e-9)
    assert axes["c"] == pytest.approx(c_deg, abs=0.5e-6 + 1e-12)


def test_word_order_is_high_word_first():
    assert i32_words(0x12345678) == [0x1234, 0x5678]
    assert i32_words(-2) == [0xFFFF, 0xFFFE]
    assert words_i32(0xFFFF, 0xFFFE) == -2
    assert text_words("G01", 2) == [0x4730, 0x3100]


# ---------------------------------------------------------------------------- independent peer

@pytest.mark.peer
async def test_mbpoll_reads_and_writes_the_map(sim):
    mbpoll = shutil.which("mbpoll")
    if mbpoll is None:
        pytest.skip("mbpoll not installed (.ci/install-peers.sh installs it)")
    ctrl, fe, port, link = sim
    await link.connect()
    job = make_job(ctrl.truth, DIALECT)
    _ = [h async for h in link.run(job)]
    in_slot0 = max(n for n in range(1, job.touch_count + 1) if (n - 1) % 16 == 0)

    async def run(*args: str) -> str:
        proc = await asyncio.create_subprocess_exec(
            mbpoll, "-m", "tcp", "-a", "1", "-p", str(port), "-1", "-0", *args,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        out, err = await asyncio.wait_for(proc.communicate(), 20)
        assert proc.returncode == 0, err.decode()
        return out.decode()

    out = await run("-t", "4", "-r", "0", "-c", "2", "127.0.0.1")
    assert re.search(r"\[0\]:\s+" + str(MAP_ID), out) and re.search(r"\[1\]:\s+1\b", out)
    x_ref = slot_address(0) + 2
    out = await run("-t", "4:int", "-B", "-r", str(x_ref), "-c", "1", "127.0.0.1")
    expected = round(ctrl.touches[in_slot0 - 1].latched["X"] * LINEAR_COUNTS_PER_MM)
    assert re.search(rf"\[{x_ref}\]:\s+{expected}\b", out), out
    await run("-t", "4", "-r", str(addr("BUSY")), "127.0.0.1", "1")
    await until(lambda: ctrl.busy)
    proc = await asyncio.create_subprocess_exec(  # a CNC-owned register refuses the write
        mbpoll, "-m", "tcp", "-a", "1", "-p", str(port), "-1", "-0", "-t", "4", "-r",
        str(addr("STATE")), "127.0.0.1", "4", stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE)
    out, err = await proc.communicate()
    assert proc.returncode != 0 or "Illegal" in (out + err).decode()
    assert fe.regs[addr("STATE")] == 4  # done, unchanged by the refused write


async def test_disconnect_mid_stream_is_a_link_error_and_the_next_run_succeeds(sim):
    from simulators.faults import Fault, FaultPlan

    ctrl, _, _, link = sim
    await link.connect()
    ctrl.faults = FaultPlan([Fault(kind="disconnect", at_block=30)])
    with pytest.raises(LinkError, match="modbus"):
        _ = [h async for h in link.run(make_job(ctrl.truth, DIALECT))]
    await link.abort()  # may fail silently: the connection is gone
    await link.close()
    ctrl.faults = FaultPlan()
    assert ctrl.state == "running"  # starved mid-program; BEGIN of the next run resets it
    await link.connect()  # what the daemon's reconnector does before the next run
    job = make_job(ctrl.truth, DIALECT)
    hits = [h async for h in link.run(job)]
    latched_equal(hits, ctrl, job, tol_mm=0.5 / LINEAR_COUNTS_PER_MM + 1e-9)


@pytest.mark.parametrize("dialect", ["fanuc", "haas", "siemens", "heidenhain", "linuxcnc"])
async def test_every_dialect_streams_through_the_mailbox(dialect):
    ctrl, job = real_setup(dialect)
    fe = ModbusFrontend(ctrl)
    link = ModbusLink(ModbusLinkConfig(transport="modbus", port=await fe.start()))
    await link.connect()
    try:
        hits = [h async for h in link.run(job)]
    finally:
        await link.close()
        await fe.stop()
    latched_equal(hits, ctrl, job, tol_mm=0.5 / LINEAR_COUNTS_PER_MM + 1e-9)
