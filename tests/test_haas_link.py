"""Haas NGC data port: the daemon's link against the simulator's data port on a free loopback
port — program onto the share, cycle start left to the machine (and said so), results from the
macro variables, stop, RESET, verdict, the port's "answers to every connection" caught — and
the port's answers fuzzed (tracebacks 0, hangs 0, wrong acceptances 0)."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchmarks.rigs.transport_sim import latched_equal, make_truth
from contracts.jobs import ProgramJob, Verdict
from contracts.setup_files import plan_from_dict
from contracts.yaml_files import ConfigError
from drivers.base import ControllerAborted, LinkError
from drivers.haas.link import HaasLink
from drivers.haas.port import DataPort, clean, parse_macro, parse_status
from drivers.haas.schema import HaasLinkConfig
from drivers.registry import link_config
from programs.generate import generate
from simulators.controller import VirtualController
from simulators.frontends.haas import HaasFrontend


def job_for(truth, poses=((0.0, 0.0), (30.0, 60.0)), handshake: bool = True) -> ProgramJob:
    plan = plan_from_dict({"name": "haas-test", "poses": [list(p) for p in poses],
                           "stylus_diameter_mm": truth.errors.probe.stylus_diameter_mm})
    g = generate(truth.machine, truth.machine_file, truth.artefact, plan, "haas",
                 handshake=handshake)
    table = g.touch_table()
    return ProgramJob(run_id="t", text=g.text, dialect="haas", touch_count=len(table),
                      touches=table, codec=g.dialect)


@pytest.fixture(scope="module")
def truth():
    return make_truth()


async def rig(truth, tmp_path, **kw):
    ctrl = VirtualController(truth, dialect="haas")
    fe = HaasFrontend(ctrl, tmp_path, **kw)
    port = await fe.start()
    cfg = HaasLinkConfig(transport="haas", host="127.0.0.1", port=port, program_dir=tmp_path,
                         poll_interval_s=0.02, connect_timeout_s=3)
    return ctrl, fe, HaasLink(cfg)


async def until(pred, timeout_s: float = 10.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not pred():
            await asyncio.sleep(0.01)


async def test_results_from_macro_variables_after_the_machines_cycle_start(truth, tmp_path):
    ctrl, fe, link = await rig(truth, tmp_path, auto_start=False)
    steps: list = []
    link.on_step = steps.append
    await link.connect()
    job = job_for(truth)
    got: list = []

    async def consume() -> None:
        got.extend([h async for h in link.run(job)])
    task = asyncio.create_task(consume())
    try:
        await until(lambda: bool(steps))
        await asyncio.sleep(0.3)
        assert "waiting for cycle start" in steps[0] and ctrl.state == "idle" and not got
        assert (tmp_path / "O09100.nc").read_bytes() == job.text.replace(
            "\n", "\r\n").encode("ascii")  # CR LF as the control writes its programs
        assert ctrl.variables["#693"] == 1.0  # program-ready for the routine
        await fe.cycle_start()
        async with asyncio.timeout(60):
            await task
        latched_equal(got, ctrl, job, tol_mm=1e-6)  # the port prints 6 decimals
        assert fe.pacer.holds >= 1 and ctrl.variables["#688"] == float(job.touch_count)
        await link.write_verdict(Verdict("PASS", "r"))
        assert ctrl.verdict == 1 and ctrl.variables["#598"] == 1.0 and ctrl.done
    finally:
        task.cancel()
        await link.close()
        await fe.stop()


async def test_stop_and_reset(truth, tmp_path):
    ctrl, fe, link = await rig(truth, tmp_path)
    await link.connect()
    try:
        agen = link.run(job_for(truth))
        assert (await anext(agen)).seq == 1
        await link.abort()  # #689 = 1: M30 at the next touch, no alarm
        assert ctrl.state == "done" and ctrl.alarm is None
        with pytest.raises(LinkError, match="stop request"):
            async for _ in agen:
                pass
        got = []
        with pytest.raises(ControllerAborted, match="RESET"):
            async for h in link.run(job_for(truth)):
                got.append(h)
                if len(got) == 2:
                    await ctrl.abort()
        assert [h.seq for h in got] == list(range(1, len(got) + 1))
    finally:
        await link.close()
        await fe.stop()


async def test_another_client_on_the_data_port_is_caught_not_misread(truth, tmp_path):
    """The control sends every answer to all connections: a second client's answer arriving
    before ours fails the request instead of being taken for our variable."""
    ctrl, fe, link = await rig(truth, tmp_path)
    await link.connect()
    other = DataPort("127.0.0.1", link.cfg.port, 2.0)
    await other.connect()
    try:
        ctrl.variables["#599"] = 7.0
        await other.request("?Q100")  # its answer reaches our connection too
        await asyncio.sleep(0.1)
        with pytest.raises(LinkError, match="another client"):
            await link._read(599)
        assert await link._read(599) == 7.0  # the next request is in step again
    finally:
        await other.close()
        await link.close()
        await fe.stop()


async def test_a_request_stopped_before_its_answer_leaves_the_port_in_step(truth, tmp_path):
    """A run stopped while it polls (its task cancelled with ``?Q600`` sent, the answer not yet
    read): that answer arrives later and must be dropped, not taken for the stop request's
    answer nor reported as another client's ("unexpected line 'MACRO, …' before '?E…'")."""
    ctrl, fe, link = await rig(truth, tmp_path)
    await link.connect()
    try:
        ctrl.variables["#599"] = 3.0
        for _ in range(3):
            t = asyncio.create_task(link._read(599))
            for _ in range(100):  # (the answers still owed are read first: a few loop turns)
                await asyncio.sleep(0)
                if link._port._waiting:
                    break
            # sent, its answer not read yet (that needs the server's turn, then ours)
            assert not t.done() and link._port._waiting
            t.cancel()
            with pytest.raises(asyncio.CancelledError):
                await t
        await link._write(689, 1.0)  # what abort() writes first
        assert ctrl.variables["#689"] == 1.0
        assert await link._read(599) == 3.0 and link._port._owed == 0
    finally:
        await link.close()
        await fe.stop()


async def test_stop_while_the_run_polls(truth, tmp_path):
    """The session stops a run by cancelling the task that reads it, then calls abort(): at
    whatever point of its polling the run was, the stop reaches the control."""
    for delay_s in (0.0, 0.005, 0.013, 0.031):
        ctrl, fe, link = await rig(truth, tmp_path)
        await link.connect()
        try:
            got: list = []

            async def consume(link: HaasLink = link, got: list = got) -> None:
                async for h in link.run(job_for(truth)):
                    got.append(h)
            task = asyncio.create_task(consume())
            await until(lambda got=got: len(got) >= 1)
            await asyncio.sleep(delay_s)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            await link.abort()
            assert ctrl.state in ("done", "idle") and ctrl.alarm is None, delay_s
            assert await link._read(599) >= 1.0  # in step for the next run
        finally:
            await link.close()
            await fe.stop()


async def test_legacy_numbering_and_refused_writes(truth, tmp_path):
    ctrl = VirtualController(truth, dialect="haas")
    fe = HaasFrontend(ctrl, tmp_path, variable_base=0)  # a control on the legacy numbers
    cfg = HaasLinkConfig(transport="haas", host="127.0.0.1", port=(await fe.start()),
                         program_dir=tmp_path, variable_base=0)
    link = HaasLink(cfg)
    await link.connect()
    try:
        ctrl.variables["#599"] = 3.0
        assert await link._read(599) == 3.0
        with pytest.raises(LinkError, match="refused"):
            await link._port.write(5021, 1.0)  # a position: the port may not write it
    finally:
        await link.close()
        await fe.stop()


async def test_config_errors_name_the_key(tmp_path):
    base = {"transport": "haas", "host": "10.0.0.24", "program_dir": str(tmp_path)}
    for extra, match in (({"variables": {"request": 600}}, "not a free common variable"),
                         ({"variables": {"reqest": 690}}, "unknown role"),
                         ({"variable_base": 5000}, "variable_base"),
                         ({"port": 70000}, "port")):
        with pytest.raises(ConfigError, match=match):
            link_config({**base, **extra})
    with pytest.raises(ConfigError, match="program_dir"):
        link_config({"transport": "haas", "host": "10.0.0.24"})


answers = st.one_of(
    st.text(max_size=40),
    st.builds(lambda v: f"MACRO, {v}", st.one_of(
        st.floats(allow_nan=True, allow_infinity=True).map(repr),
        st.sampled_from(["", "1e999", "12.5.3", "--1", "0x10", "1,5", " 7 "]))),
    st.builds(lambda a, b: f"\x02{a}\x17>{b}", st.text(max_size=10), st.text(max_size=10)))


@settings(max_examples=400, deadline=None)
@given(answers)
def test_port_answer_garbage_is_a_number_or_a_clear_error(answer):
    """Whatever the data port answers: a finite number exactly as printed, or LinkError."""
    line = clean(answer.encode("ascii", errors="replace"))
    try:
        value = parse_macro(line, 10599)
    except LinkError as e:
        assert "10599" in str(e) or "MACRO" in str(e)
    else:
        assert math.isfinite(value) and line.startswith("MACRO,")
    try:
        state, _ = parse_status(line)
    except LinkError:
        pass
    else:
        assert state and (state == "BUSY" or line.startswith("PROGRAM,"))


@settings(max_examples=25, deadline=None)
@given(st.binary(min_size=1, max_size=300))
def test_a_port_answering_garbage_bytes_fails_clearly_within_its_timeout(garbage):
    """A data port (or a device on its port) answering anything: a request ends with a value
    or LinkError within the request timeout — never hangs, never raises anything else."""
    async def one() -> None:
        async def serve(reader, writer):
            with_line = garbage if garbage.endswith(b"\n") else garbage + b"\r\n"
            try:
                while await reader.readline():
                    writer.write(with_line)
                    await writer.drain()
            except ConnectionError:
                pass
        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = DataPort("127.0.0.1", server.sockets[0].getsockname()[1], 0.5)
        try:
            await port.connect()
            async with asyncio.timeout(5):
                try:
                    value = await port.read(10599)
                    assert math.isfinite(value)
                except LinkError:
                    pass
        finally:
            await port.close()
            server.close()
            await server.wait_closed()

    asyncio.run(one())


async def test_temperature_from_a_macro_variable_the_machine_copies_a_sensor_into(truth,
                                                                                 tmp_path):
    from contracts.temperatures import TemperatureChannel

    ctrl, fe, link = await rig(truth, tmp_path)
    await link.connect()
    try:
        ctrl.variables["#593"] = 21.75
        ch = TemperatureChannel(name="spindle", address="#593")
        assert await link.read_temperature(ch) == pytest.approx(21.75, abs=1e-6)
    finally:
        await link.close()
        await fe.stop()


def test_the_share_folder_is_relative_to_daemon_yaml_as_every_other_path(tmp_path,
                                                                          monkeypatch):
    from daemon.machines.setup import validate_link

    etc = tmp_path / "etc" / "rumba"
    etc.mkdir(parents=True)
    monkeypatch.chdir(tmp_path)  # rumba started elsewhere than the configuration's folder
    cfg = validate_link({"transport": "haas", "host": "10.0.0.24", "program_dir": "share"},
                        "machines[0].link", etc)
    assert Path(cfg.program_dir) == etc / "share"
    absolute = tmp_path / "mnt" / "haas"
    cfg = validate_link({"transport": "haas", "host": "10.0.0.24",
                         "program_dir": str(absolute)}, "machines[0].link", etc)
    assert Path(cfg.program_dir) == absolute
