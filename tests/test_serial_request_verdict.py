"""Serial DNC start-of-shift request and verdict write-back: the request-line grammar, the
dialects' verdict programs run by the simulator's executor, and the driver against the
simulator's serial front-end and the real VirtualController over a real pty and TCP."""

from __future__ import annotations

import asyncio
import shutil
import subprocess
import time

import pytest

from benchmarks.rigs.transport_sim import (
    MACRO_VERDICT_VARIABLE,
    first_touch_of,
    make_truth,
    real_setup,
)
from contracts.jobs import Verdict
from contracts.result_lines import DIALECT_NAMES
from drivers.base import LinkError
from drivers.serial.link import SerialDncLink, parse_request
from drivers.serial.schema import SerialLinkConfig
from programs.dialects import get_dialect
from programs.geometry import ProgramError
from simulators.controller import VERDICT_VARIABLE, VirtualController
from simulators.frontends.serial import SerialFrontend, SerialSettings
from tests.waiting import settle, until

# ------------------------------------------------------------------------ request grammar


@pytest.mark.parametrize(("line", "machine"), [
    ("RUMBA REQUEST MILL1", "MILL1"),
    ("  RUMBA  REQUEST\tmill_2.a-b \r\n", "mill_2.a-b"),  # DPRNT padding, CR LF
    ("RUMBA 1 0 0 B1 1 1 1 2 3 4 5", None),  # a result line is not a request
    ("ALARM: 3001", None),
    ("", None),
])
def test_request_line_grammar(line, machine):
    assert parse_request(line) == machine


@pytest.mark.parametrize("line", [
    "RUMBA REQUEST",  # no machine
    "RUMBA REQUEST MILL1 EXTRA",
    "RUMBA REQUEST MI(LL)1",
    "RUMBA REQUEST " + "M" * 33,
    "rumba request m~l1",  # line noise
])
def test_broken_request_line_is_refused_not_guessed(line):
    with pytest.raises(ValueError, match="RUMBA REQUEST <machine>"):
        parse_request(line)


# ------------------------------------------------------------------------ verdict programs


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_verdict_program_is_tiny_and_takes_only_a_code(dialect):
    d = get_dialect(dialect)
    # the simulator reads the one the macros read (gcode_templates/*/README.md)
    assert d.verdict_variable == VERDICT_VARIABLE[dialect] == MACRO_VERDICT_VARIABLE[dialect]
    text = d.verdict_program(3)
    assert len(text.splitlines()) <= 5 and d.verdict_variable in text
    for bad in (0, 5, True, 2.0, "1", "1\nM30"):
        with pytest.raises(ProgramError, match="verdict code"):
            d.verdict_program(bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
async def test_executor_running_the_verdict_program_delivers_the_verdict(dialect):
    vc = VirtualController(make_truth(), dialect=dialect)
    vc.raise_start_request()
    assert (vc.verdict, vc.done) == (0, False)
    await vc.load_program(get_dialect(dialect).verdict_program(2), dialect)
    await vc.start()
    assert await vc.wait_done(5) == "done", vc.alarm
    assert (vc.verdict, vc.done) == (2, True)
    assert vc.variables[VERDICT_VARIABLE[dialect]] == 2.0


async def test_verdict_written_by_a_front_end_shows_in_the_macro_variable():
    vc = VirtualController(make_truth(), dialect="siemens")
    vc.verdict = 4  # what the OPC UA / Modbus front-ends do when the daemon writes it
    assert vc.variables["R4"] == 4.0
    vc.raise_start_request()  # the macro clears it before asking
    assert vc.variables["R4"] == 0.0 and vc.verdict == 0


@pytest.mark.peer
@pytest.mark.skipif(shutil.which("rs274") is None, reason="rs274 not installed (LinuxCNC "
                    "peer: `make peers` installs linuxcnc-uspace)")
def test_linuxcnc_verdict_program_accepted_by_rs274(tmp_path):
    src = tmp_path / "v.ngc"
    src.write_text(get_dialect("linuxcnc").verdict_program(1) + "\n")
    r = subprocess.run(["rs274", "-g", str(src), str(tmp_path / "out.txt")],
                       stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=60,
                       cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "PROGRAM_END" in (tmp_path / "out.txt").read_text()


# ------------------------------------------------------------------------ driver over a pty


async def serial_rig(vc, tcp: bool = False, baud: int = 115200, **link_kw):
    fe = SerialFrontend(vc, SerialSettings(baudrate=baud, framing="7E1"))
    url = f"socket://127.0.0.1:{await fe.open_tcp()}" if tcp else await fe.open_pty()
    name = link_kw.pop("dialect", vc.dialect)
    dialect = get_dialect(name) if name else None
    link = SerialDncLink(SerialLinkConfig(transport="serial", url=url, baudrate=baud,
                                          **link_kw), dialect=dialect)
    await link.connect()
    return fe, link


@pytest.mark.parametrize("tcp", [False, True], ids=["pty", "socket"])
async def test_start_request_then_verdict_program_over_the_line(tcp):
    vc = VirtualController(make_truth(), dialect="fanuc")
    fe, link = await serial_rig(vc, tcp=tcp)
    try:
        assert link.capabilities.start_request and link.capabilities.writes_verdict
        waiter = asyncio.create_task(link.wait_start_request())
        await settle()
        assert not waiter.done()  # nothing asked yet
        vc.raise_start_request()
        req = await asyncio.wait_for(waiter, 5)
        assert (req.source, req.machine) == ("cnc", vc.machine_id)
        assert "RUMBA REQUEST" in req.detail
        await link.write_verdict(Verdict("WARN", "r1"))
        async with asyncio.timeout(5):
            while not vc.done:
                await asyncio.sleep(0.01)
        assert vc.verdict == 2 and vc.variables["#598"] == 2.0
    finally:
        await link.close()
        await fe.close()


async def test_other_lines_and_other_machines_never_start_a_run():
    vc = VirtualController(make_truth(), dialect="fanuc")
    fe, link = await serial_rig(vc, request_machine="MILL7")
    try:
        waiter = asyncio.create_task(link.wait_start_request())
        vc.output("RUMBA 1 0 0 B1 1 1 1.0 2.0 3.0 0.0 0.0")  # stray result line
        vc.output("RUMBA REQUEST MI~L7")  # garbled request
        vc.raise_start_request()  # the simulated CNC names itself THESIS_WCBXFZYT
        await until(lambda: list(link._proto.unsolicited)[-1:] == [
            f"RUMBA REQUEST {vc.machine_id}"], 10, "the three lines read")
        await settle()
        assert not waiter.done()
        assert list(link._proto.unsolicited)[-3:] == [
            "RUMBA 1 0 0 B1 1 1 1.0 2.0 3.0 0.0 0.0", "RUMBA REQUEST MI~L7",
            f"RUMBA REQUEST {vc.machine_id}"]
        vc.machine_id = "mill7"  # names are compared case-insensitively
        vc.raise_start_request()
        req = await asyncio.wait_for(waiter, 5)
        assert req.machine == "mill7"
    finally:
        await link.close()
        await fe.close()


async def test_after_an_aborted_stream_no_verdict_is_fed_into_the_old_program():
    """Abort: the link finishes the block it is sending and closes the tape (``%``),
    so the control ends the old program at that block — never a truncated block, never the
    rest of the program — and reads the verdict as a tape of its own; the next run needs no
    RESET at the control."""
    # 115 200 baud: the 2-pose program (≈ 2 s on the line) still streams at the first touch.
    vc, job = real_setup("siemens", poses=((0.0, 0.0), (30.0, 0.0)))
    vc.raise_start_request()
    fe, link = await serial_rig(vc, baud=115200)
    try:
        agen = link.run(job)
        assert (await asyncio.wait_for(anext(agen), 20)).seq == 1
        await link.abort()  # e.g. the operator pressed Abort on the HMI
        await agen.aclose()
        assert await vc.wait_done(10) == "done", vc.alarm  # the old program ended at the cut
        assert len(vc.touches) < job.touch_count  # its tail was never sent
        assert vc.variables["R4"] == 0.0  # nothing was released by the old program
        await link.write_verdict(Verdict("ERROR", "r1", "aborted"))
        async with asyncio.timeout(5):
            while vc.verdict != 4:
                await asyncio.sleep(0.01)
        assert vc.variables["R4"] == 4.0  # ERROR, from the verdict's own tape
        _, job2 = real_setup("siemens")
        hits = [h async for h in link.run(job2)]
        assert len(hits) == job2.touch_count and hits[0].seq == 1
        # the last result line comes before the control has run the closing blocks
        assert await vc.wait_done(10) == "done"
        await link.write_verdict(Verdict("PASS", "r2"))
        async with asyncio.timeout(5):
            while vc.verdict != 1:
                await asyncio.sleep(0.01)
        assert vc.variables["R4"] == 1.0
    finally:
        await link.close()
        await fe.close()


async def test_request_during_a_run_is_refused_and_a_lost_line_ends_the_wait():
    vc, job = real_setup("fanuc", errors={"absent_balls": ["B2"]})
    fe, link = await serial_rig(vc)
    try:
        got = []
        with pytest.raises(Exception, match="did not trigger"):
            async for h in link.run(job):
                if h.seq == 1:
                    vc.raise_start_request()  # the CNC cannot ask while running our program
                got.append(h)
        assert got[-1].seq == first_touch_of(job, "B2")
        assert link._proto.requests.empty()
        assert not link._tape_open  # the control in alarm dropped the tape itself
        waiter = asyncio.create_task(link.wait_start_request())
        await settle()
        await fe.close()  # the line goes away
        with pytest.raises(LinkError, match="closed"):
            await asyncio.wait_for(waiter, 5)
    finally:
        await link.close()
        await fe.close()


async def test_verdict_needs_a_dialect():
    vc = VirtualController(make_truth(), dialect="fanuc")
    fe, link = await serial_rig(vc, dialect=None)
    try:
        with pytest.raises(LinkError, match="no dialect"):
            await link.write_verdict(Verdict("PASS", "r1"))
    finally:
        await link.close()
        await fe.close()


async def _until(cond, what: str, timeout_s: float = 10.0) -> None:
    """Poll ``cond()`` (the simulated control prints asynchronously); fails naming ``what``."""
    try:
        async with asyncio.timeout(timeout_s):
            while not cond():
                await asyncio.sleep(0.005)
    except TimeoutError:
        raise AssertionError(f"{what}: not all received within {timeout_s:g} s") from None


async def test_a_burst_of_request_lines_is_one_request_and_repeats_are_refused():
    vc, job = real_setup("fanuc")
    # request_holdoff_s from the link's configuration: "just finished" for the whole test
    fe, link = await serial_rig(vc, baud=115200, request_holdoff_s=3600.0)
    proto = link._proto
    line = f"RUMBA REQUEST {vc.machine_id}"

    async def burst(n: int = 50) -> None:
        seen = proto.requests_seen + n
        for _ in range(n):
            vc.output(line)  # the macro printing its request line in a loop
        await _until(lambda: proto.requests_seen >= seen, "request lines")

    try:
        await burst()
        assert proto.requests.qsize() == 1 and proto.requests_refused == 49
        req = await asyncio.wait_for(link.wait_start_request(), 5)
        assert req.machine == vc.machine_id
        await burst()  # served, run not started yet: refused
        assert proto.requests.empty()
        hits = []
        async for h in link.run(job):
            if h.seq == 1:
                for _ in range(50):
                    vc.output(line)  # during the run
            hits.append(h)
        assert len(hits) == job.touch_count
        await link.write_verdict(Verdict("PASS", "r1"))
        await burst()  # just finished
        waiter = asyncio.create_task(link.wait_start_request())  # the service asks again
        await burst()  # still within the hold-off
        assert proto.requests.empty() and not waiter.done()
        assert proto.requests_seen == 250 and proto.requests_refused == 249
        proto.holdoff_until = 0.0  # the hold-off has passed
        await burst()
        req2 = await asyncio.wait_for(waiter, 5)
        assert req2.machine == vc.machine_id and proto.requests.empty()
    finally:
        await link.close()
        await fe.close()


@pytest.mark.parametrize("holdoff_s", [0.0, 7.5])
def test_request_holdoff_comes_from_the_link_configuration(holdoff_s):
    link = SerialDncLink(SerialLinkConfig(transport="serial", url="socket://127.0.0.1:9",
                                          request_holdoff_s=holdoff_s))
    t0 = time.monotonic()
    link._run_ended()
    assert t0 + holdoff_s <= link._holdoff_until <= time.monotonic() + holdoff_s
