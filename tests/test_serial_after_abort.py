"""After a DNC program is stopped early, the next tape waits until the control ended it (the
simulator's serial front-end on a pty, the real link). Plain DNC has no remote reset: the
control executes the blocks it already holds and prints their result lines; the next run took
those for its own — the stopped program's seq 1 as the new one's (its latches, silently), then
"result line of touch seq 1 lost" or a duplicate. Now the link reads the stopped program's
remaining lines up to the last one its fed bytes can print before the next tape, and the next
run's hits are all and only its own program's. (Heidenhain is left out: the simulated TNC does
not end a program cut before its END PGM, old and new link alike.)"""

from __future__ import annotations

import asyncio
import logging

import pytest

from benchmarks.rigs.transport_sim import make_job, make_truth
from drivers.serial.link import SerialDncLink
from drivers.serial.schema import SerialLinkConfig
from simulators.controller import VirtualController
from simulators.frontends.serial import SerialFrontend, SerialSettings

POSES = ((0.0, 0.0), (30.0, 60.0))


async def _consume(link: SerialDncLink, job, hits: list) -> None:
    async for hit in link.run(job):
        hits.append(hit)


@pytest.mark.asyncio
@pytest.mark.parametrize("dialect", ["fanuc", "siemens"])
@pytest.mark.parametrize("stop", ["fed-whole", "cut"])
async def test_the_next_tape_waits_for_the_stopped_program_to_end(dialect, stop, caplog):
    """``fed-whole``: the whole tape is in the control's buffer when the run stops after its
    first hit (the failure seen: the next run read the old program's seq 2 and ended
    INTERRUPTED "result line of touch seq 1 lost"); ``cut``: the stop comes while the tape is
    fed, before any result, and the tape is closed at a block's end."""
    truth = make_truth()
    job = make_job(truth, dialect, POSES if stop == "cut" else POSES[:1])
    vc = VirtualController(truth, time_scale=0.3, dialect=dialect)
    vc.files.update(job.files)
    # a DNC receive buffer of 4 KiB, or one that holds the whole one-pose program
    fe = SerialFrontend(vc, SerialSettings(baudrate=115200, framing="7E1", rx_buffer_bytes=(
        4096 if stop == "cut" else 32768)))
    link = SerialDncLink(SerialLinkConfig(transport="serial", url=await fe.open_pty(),
                                          baudrate=115200, framing="7E1", result_timeout_s=60))
    await link.connect()
    caplog.set_level(logging.INFO, logger="rumba.serial")
    try:
        first: list = []
        run1 = asyncio.create_task(_consume(link, job, first))
        if stop == "cut":
            # the control holds the blocks of the first touches, none of them printed yet
            marks = {"fanuc": "DPRNT[RUMBA*", "siemens": 'RLINE="RUMBA '}
            third = [i for i in range(len(job.text))
                     if job.text.startswith(marks[dialect], i)][2]
            while link.bytes_sent <= third + 200:
                assert not run1.done(), run1
                await asyncio.sleep(0.001)
            assert first == [], first
        else:
            # the tape fed whole, a first hit in: the control runs on through the buffer
            while not (first and link._sender is not None and link._sender.done()):
                assert not run1.done(), run1
                await asyncio.sleep(0.001)
            assert len(first) < job.touch_count - 3, len(first)
        run1.cancel()  # the operator's abort, as the session makes it
        await asyncio.wait({run1})
        await link.abort()  # a cut tape closed at a block's end (once the control made room)
        assert vc.state in ("running", "hold"), vc.state  # it runs on through what it holds
        # the next run at once, as a new start would: no waiting for the control here
        second: list = []
        await asyncio.wait_for(_consume(link, job, second), 300)
        assert await vc.wait_done(60) == "done"
    finally:
        await link.close()
        await fe.close()
    n = job.touch_count
    assert [h.seq for h in second] == list(range(1, n + 1))
    # the second run's hits are the controller's touches of the second program, latch for
    # latch (touch noise makes a touch of the stopped program differ from its namesake)
    assert len(vc.touches) == n
    for hit, touch in zip(second, vc.touches, strict=True):
        for k in "XYZ":
            assert abs(hit.axes[k] - touch.latched[k]) <= 0.5e-4 + 1e-9, (hit.seq, k)
    drained = [r for r in caplog.records if "result of the stopped program" in r.getMessage()]
    assert drained, "the stopped program printed nothing after the stop: nothing tested"


@pytest.mark.parametrize("dialect", ["fanuc", "siemens", "heidenhain", "linuxcnc"])
def test_the_last_touch_a_fed_part_of_a_program_prints(dialect):
    """``last_printed_seq``: the seq of the last result print statement in a program's first
    bytes (the counter = seq line, then the print), for every dialect's program text."""
    job = make_job(make_truth(), dialect, POSES)
    text, codec = job.text, job.codec
    assert codec.last_printed_seq(text) == job.touch_count
    lines = text.splitlines(keepends=True)
    seen = [codec.last_printed_seq("".join(lines[:k])) for k in range(0, len(lines) + 1, 7)]
    assert seen[0] == 0 and seen == sorted(seen) and len(set(seen)) > job.touch_count // 2
    # a cut just before a touch's print: that touch is not counted, the one before is
    marks = {"fanuc": "DPRNT[RUMBA*", "siemens": 'WRITE(RERR,"RUMBA_RES",RLINE)',
             "heidenhain": "FN 16: F-PRINT RUMBA_", "linuxcnc": "(LOG,RUMBA "}
    prints = [k for k, ln in enumerate(lines) if marks[dialect] in ln
              and (dialect != "siemens" or lines[k - 1].startswith('RLINE="RUMBA '))]
    assert len(prints) == job.touch_count
    assert codec.last_printed_seq("".join(lines[:prints[4]])) == 4
    assert codec.last_printed_seq("".join(lines[:prints[4] + 1])) == 5
