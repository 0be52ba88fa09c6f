"""A run stopped while a pose's temperature read waits (found in review): the read is cancelled
and awaited before the run reports itself ABORTED — journaled as cut by the stop, its
transmitter connection closed, no task of it left running — and a value that had already come
when the stop arrived is journaled, not lost. End to end: the warming CNC behind its real
asyncua front-end, a real Modbus TCP socket that answers the start and then falls silent, the
abort through the HMI's HTTP API as an operator sends it, the control held in feed hold before
the next pose so that the abort meets the pose it is meant to."""

from __future__ import annotations

import asyncio
import re
from collections.abc import AsyncIterator

import aiohttp
import pytest
import pytest_asyncio
import yaml

from benchmarks.rigs.e2e_run import RUN_TIMEOUT_S
from benchmarks.rigs.temperature_helpers import (
    SilentTransmitter,
    column,
    one_channel_recorder,
    silent_transmitter,
)
from benchmarks.rigs.warm_cnc import SPINDLE, machine_entry
from contracts.temperatures import TemperatureChannel, TemperatureReading
from daemon.config import load_daemon_config
from daemon.run import temperatures as run_temperatures
from daemon.run.phases import END_READS, START_READS
from daemon.run.session import State
from daemon.run.temperatures import STOPPED, TemperatureRecorder
from daemon.service.service import Service
from daemon.store.journal import Store
from daemon.store.temperatures import temperatures
from simulators.controller import VirtualController
from simulators.faults import Fault, FaultPlan
from tests.test_temperature_channels import cnc

__all__ = ["cnc"]  # the warming CNC fixture, shared with the channels' end-to-end tests

TOKEN = "t0k3n-for-abort-tests-0123456789"


@pytest_asyncio.fixture
async def silent_after_start() -> AsyncIterator[tuple[SilentTransmitter, int]]:
    """A transmitter that answers the run's start read, then never again."""
    async with silent_transmitter(answer_first=1) as served:
        yield served


def hold_before_pose(ctrl: VirtualController, pose: int, monkeypatch: pytest.MonkeyPatch
                     ) -> None:
    """The next program ``ctrl`` loads stands in feed hold at its header of pose ``pose`` (as
    an operator holds a machine), after every touch before it and before any of the pose's own,
    until the abort. At time_scale 0 the simulator probes a pose's 20 touches in ~10 ms of wall
    time: without the hold the run was often at pose 1 by the time the test, polling, saw pose
    0's read on the wire (pose 1 journaled "the previous read of this channel is still
    waiting", as it should) or had sent its abort: 30 of 70 runs of this test alone failed."""
    load = ctrl.load_program

    async def load_holding(text: str, dialect: str, files: dict[str, str] | None = None
                           ) -> None:
        lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
        block = next((i for i, line in enumerate(lines, 1)  # the simulator's block numbers
                      if re.search(rf"\bPOSE {pose}\b", line)), None)
        if block is None:
            raise ValueError(f"the program has no POSE {pose}: nowhere to hold it")
        ctrl.faults = FaultPlan([Fault(kind="feed_hold", at_block=block)])
        await load(text, dialect, files)

    monkeypatch.setattr(ctrl, "load_program", load_holding)


def column_rows(store: Store, run_id: str | None) -> list[TemperatureReading]:
    return [] if run_id is None else [r for r in temperatures(store, run_id)
                                      if r.channel == "column"]


async def started_service(rig, port: int, tmp_path) -> Service:
    """The daemon started on ``rig``'s machine: its controller's spindle channel and the column
    transmitter on ``port`` (30 s timeout), its HMI on a free loopback port, in ``tmp_path``."""
    channels = [{"name": "spindle", "source": "controller", **SPINDLE[rig.transport]},
                column(port, timeout_s=30.0)]
    doc = {"store": {"path": str(tmp_path / "journal.sqlite")},
           "reports_dir": str(tmp_path / "reports"),
           "hmi": {"host": "127.0.0.1", "port": 0, "token": TOKEN},
           "machines": [machine_entry(rig.link, channels, {})]}
    path = tmp_path / "daemon.yaml"
    path.write_text(yaml.safe_dump(doc, allow_unicode=True), encoding="utf-8")
    service = Service(load_daemon_config(path))
    await service.start()
    return service


async def abort_via_hmi(service: Service, run_id: str
                        ) -> tuple[dict, aiohttp.ClientResponse, dict, dict]:
    """The HMI's status of mill1 just before, then its abort (response and body) and the
    run's record after it, as the page and an operator's button get them."""
    async with aiohttp.ClientSession() as http:
        auth = {"Authorization": f"Bearer {TOKEN}"}
        live = (await (await http.get(service.hmi_url + "api/status",
                                      headers=auth)).json())["mill1"]
        r = await http.post(service.hmi_url + "api/machines/mill1/abort", headers=auth)
        body = await r.json()
        listed = await (await http.get(service.hmi_url + f"api/runs/{run_id}",
                                       headers=auth)).json()
    return live, r, body, listed


def running_reads() -> list[asyncio.Task]:
    return [t for t in asyncio.all_tasks()
            if t.get_name().startswith("temperature-") and not t.done()]


BUSY = "not read: the previous read of this channel is still waiting"
POSES = 7  # the plan's (tests.test_e2e_transports.PLAN)


def watch_end(rec: TemperatureRecorder, monkeypatch: pytest.MonkeyPatch) -> asyncio.Event:
    """Set when the run, its last touch in, enters ``rec.end``: up to the wait for the pose
    reads in flight, its first await, nothing in ``end`` yields, so the run waits there."""
    entered = asyncio.Event()
    end = rec.end

    async def end_seen(run_id: str, t_s: float) -> None:
        entered.set()
        await end(run_id, t_s)

    monkeypatch.setattr(rec, "end", end_seen)
    return entered


@pytest.mark.asyncio
@pytest.mark.parametrize("cnc", ["opcua"], indirect=True)
@pytest.mark.parametrize("held", [1, 2, None], ids=["pose0", "pose1", "end"])
async def test_an_abort_cancels_the_pose_read_in_flight_before_the_run_reports_aborted(
        cnc, silent_after_start, tmp_path, monkeypatch, held):
    """The control held before pose ``held``, the abort meets pose 0's read in flight; with
    ``held`` 2 pose 1 was probed meanwhile (the CNC never waits for a temperature), its read
    journaled as not asked while pose 0's still waits. ``held`` None: the program ran to its
    end, the abort meets the run waiting in ``end`` for pose 0's read after its last touch, and
    its reason says so, not "during CAPTURE" (tests/test_temperature_end_abort.py: the reads
    ``end`` waits for, each accounted for once)."""
    rig, _, _ = cnc
    tx, port = silent_after_start
    if held is not None:
        hold_before_pose(rig.ctrl, held, monkeypatch)  # the abort meets the run there
    probed = held or POSES  # the poses probed before the abort
    # the pose read waits for the transmitter's own 30 s timeout, not the 3 s cap: the abort
    # below surely meets it in flight, however loaded the machine running the test
    monkeypatch.setattr(run_temperatures, "READ_TIMEOUT_S", 120.0)
    service = await started_service(rig, port, tmp_path)
    try:
        session = service.sessions["mill1"]
        at_end = watch_end(session.temps, monkeypatch)
        rig.ctrl.raise_start_request()
        async with asyncio.timeout(RUN_TIMEOUT_S):  # the start answered, pose 0's read sent,
            while (tx.requests < 2 or len(column_rows(service.store, session.run_id)) < probed
                   or (held is None and not at_end.is_set())):  # the later poses seen
                if session.run_id is not None and not session.busy:
                    raise AssertionError(f"run ended before its abort: {session.reason}")
                await asyncio.sleep(0.01)
        run_id = session.run_id
        assert [(r.at, r.pose, r.error) for r in column_rows(service.store, run_id)] == [
            ("start", None, ""), *(("pose", k, BUSY) for k in range(1, probed))]  # 0's waits
        assert at_end.is_set() == (held is None)
        # the status the page gets says where the run is: CAPTURE, and after the last touch
        # the end's reads (the card shows the step), not a probe still at work
        live, r, body, listed = await abort_via_hmi(service, run_id)
        assert (live["state"], live["step"]) == (
            "CAPTURE", END_READS if held is None else None), live
        assert body["step"] is None, body  # cleared by the run's end state
        # the HMI answers once the run has ended: what it ended with is final now
        left = running_reads()
        readings = temperatures(service.store, run_id)
        journaled = service.store.run(run_id).reason
        async with asyncio.timeout(RUN_TIMEOUT_S):  # the stop closed the transmitter's socket
            while tx._tasks and not all(t.done() for t in tx._tasks):
                await asyncio.sleep(0.01)
    finally:
        await service.stop()
    # where the run was: a touch cut (held at a pose), or none (the end's reads, the program
    # done): the one text on the HMI's status, its run record, and the journal
    want = f"aborted by hmi {END_READS if held is None else 'during CAPTURE'}"
    assert r.status == 200 and body["reason"] == want, body
    assert session.state == State.ABORTED, session.reason
    assert (listed["state"], listed["reason"]) == ("ABORTED", want), listed
    assert journaled == want
    assert left == [], left  # no read of the run outlives it
    col = [r for r in readings if r.channel == "column"]
    assert [(r.at, r.pose) for r in col] == [
        ("start", None), *(("pose", k) for k in range(1, probed)), ("pose", 0)], col
    assert col[0].value_c == pytest.approx(23.5)
    assert col[-1].value_c is None and col[-1].error == STOPPED, col[-1]
    assert tx.requests == 2  # nothing asked after the stop
    spindle = [r for r in readings if r.channel == "spindle"]  # every read accounted for
    assert spindle and all(r.value_c is not None or r.error == STOPPED for r in spindle)


@pytest_asyncio.fixture
async def never_answers() -> AsyncIterator[tuple[SilentTransmitter, int]]:
    """A transmitter that never answers, not even the run's start read."""
    async with silent_transmitter(answer_first=0) as served:
        yield served


@pytest.mark.asyncio
@pytest.mark.parametrize("cnc", ["opcua"], indirect=True)
async def test_an_abort_during_the_start_reads_names_them_not_stream(
        cnc, never_answers, tmp_path, monkeypatch):
    """The run waits for its start-of-run temperatures, before its program is loaded (the
    state is STREAM already): the abort's reason says so, not "during STREAM" (no program was
    cut), the one text on the HMI's status, its run record and the journal; the status carries
    the step while the run is in it, and not after."""
    rig, _, _ = cnc
    tx, port = never_answers
    monkeypatch.setattr(run_temperatures, "READ_TIMEOUT_S", 120.0)  # held until the abort
    loaded: list[str] = []
    load = rig.ctrl.load_program

    async def load_seen(text: str, dialect: str, files: dict[str, str] | None = None) -> None:
        loaded.append(text)
        await load(text, dialect, files)

    monkeypatch.setattr(rig.ctrl, "load_program", load_seen)
    service = await started_service(rig, port, tmp_path)
    try:
        session = service.sessions["mill1"]
        rig.ctrl.raise_start_request()
        async with asyncio.timeout(RUN_TIMEOUT_S):  # the start read asked, never answered
            while tx.requests < 1:
                if session.run_id is not None and not session.busy:
                    raise AssertionError(f"run ended before its abort: {session.reason}")
                await asyncio.sleep(0.01)
        run_id = session.run_id
        live, r, body, listed = await abort_via_hmi(service, run_id)
        journaled = service.store.run(run_id).reason
        col = column_rows(service.store, run_id)
    finally:
        await service.stop()
    want = f"aborted by hmi {START_READS}"  # not "during STREAM": no program was cut
    assert r.status == 200 and body["reason"] == want and body["step"] is None, body
    assert (listed["state"], listed["reason"]) == ("ABORTED", want), listed
    assert journaled == want
    assert (live["state"], live["step"]) == ("STREAM", START_READS), live
    assert loaded == [] and tx.requests == 1  # no program reached the CNC, nothing more asked
    assert [(c.at, c.pose, c.value_c, c.error) for c in col] == [
        ("start", None, None, STOPPED)], col


class HeldLink:
    """A link whose temperature read answers when the test says so (the race of a value that
    arrives together with the stop cannot be timed on a real socket)."""

    def __init__(self) -> None:
        self.release = asyncio.Event()
        self.answered = False

    async def read_temperature(self, ch: TemperatureChannel) -> float:
        await self.release.wait()
        self.answered = True  # the read's task completes in this same step
        return 24.25


@pytest_asyncio.fixture
async def held(tmp_path) -> AsyncIterator[tuple[Store, HeldLink, TemperatureRecorder]]:
    """Run r1's recorder of one OPC UA channel read through a ``HeldLink``, on a real journal;
    closed after the test."""
    link = HeldLink()
    async with one_channel_recorder(tmp_path / "journal.sqlite", link) as (store, rec):
        yield store, link, rec


@pytest.mark.asyncio
async def test_a_value_arriving_with_the_stop_is_journaled(held):
    store, link, rec = held
    await rec.on_hit("r1", 0, 1.0)
    await asyncio.sleep(0)  # the pose read is waiting for its answer
    assert running_reads() and temperatures(store, "r1") == []
    link.release.set()
    while not link.answered:
        await asyncio.sleep(0)
    await rec.stop("r1")  # the stop meets the answer before the read could journal it
    got = temperatures(store, "r1")
    assert running_reads() == []
    assert [(r.at, r.pose, r.value_c, r.error) for r in got] == [("pose", 0, 24.25, "")]


@pytest.mark.asyncio
async def test_a_read_cancelled_before_it_ran_is_journaled_as_cut(held):
    """The stop comes right after the hit that started a pose read, before the event loop ever
    ran it: the read journals nothing itself, the stop journals it as cut."""
    store, link, rec = held
    await rec.on_hit("r1", 3, 7.5)  # the read is created, not yet run
    await rec.stop("r1")
    got = temperatures(store, "r1")
    assert running_reads() == [] and not link.answered
    assert [(r.at, r.pose, r.t_s, r.value_c, r.error) for r in got] == [
        ("pose", 3, 7.5, None, STOPPED)]
