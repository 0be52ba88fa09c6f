"""Heidenhain LSV2: pylsv2 itself against the simulator's LSV2 server (the wire format an
independent implementation expects: login, versions, parameters, buffer negotiation, file
transfer both ways, program state), then the daemon's link on it — the program and its files
transferred, NC start left to the operator (and said so), results read from the FN 16 file, the
stop program, the request and verdict files — and garbage from the control, fuzzed."""

from __future__ import annotations

import asyncio
import struct
import time

import pyLSV2
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.rigs.transport_sim import latched_equal, make_truth
from contracts.jobs import ProgramJob, Verdict
from contracts.messages import TouchId
from contracts.setup_files import plan_from_dict
from contracts.touch_table import TouchTable
from drivers.base import ControllerAborted, LinkError
from drivers.hits import HitFactory, MalformedResult
from drivers.lsv2.link import Lsv2Link
from drivers.lsv2.schema import Lsv2LinkConfig
from programs.dialects import get_dialect
from programs.generate import generate
from simulators.controller import VirtualController
from simulators.frontends.lsv2 import Lsv2Frontend, telegram

DIALECT = get_dialect("heidenhain")


def job_for(truth, poses=((0.0, 0.0), (30.0, 60.0)), handshake: bool = True) -> ProgramJob:
    plan = plan_from_dict({"name": "lsv2-test", "poses": [list(p) for p in poses],
                           "stylus_diameter_mm": truth.errors.probe.stylus_diameter_mm})
    g = generate(truth.machine, truth.machine_file, truth.artefact, plan, "heidenhain",
                 handshake=handshake)
    table = g.touch_table()
    return ProgramJob(run_id="t", text=g.text, dialect="heidenhain", touch_count=len(table),
                      touches=table, files=dict(g.aux_files), codec=g.dialect)


def cfg(port: int, **kw) -> Lsv2LinkConfig:
    return Lsv2LinkConfig(**{"transport": "lsv2", "host": "127.0.0.1", "port": port,
                             "poll_interval_s": 0.05, "connect_timeout_s": 3,
                             "stop_timeout_s": 8, **kw})


@pytest.fixture(scope="module")
def truth():
    return make_truth()


async def until(pred, timeout_s: float = 10.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not pred():
            await asyncio.sleep(0.01)


async def test_pylsv2_transfers_a_program_and_reads_results_from_the_simulated_tnc(truth,
                                                                                  tmp_path):
    """pylsv2, unchanged, is the TNCremo side: it logs in, negotiates the block length, sends
    the program and its format files, reads the program state, and reads back the result file
    the program printed — whose lines are the controller's latches."""
    ctrl = VirtualController(truth, dialect="heidenhain")
    fe = Lsv2Frontend(ctrl, auto_start=None)
    port = await fe.start()
    job = job_for(truth, poses=((0.0, 0.0),), handshake=False)
    local = tmp_path / "out"
    local.mkdir()

    def tncremo() -> tuple[str, int, str]:
        con = pyLSV2.LSV2("127.0.0.1", port=port, timeout=5, safe_mode=False)
        con.connect()
        try:
            assert con.versions.control == "TNC640" and con.parameters.max_block_length == 4096
            assert con.login(pyLSV2.Login.DNC)
            assert con.program_status() == pyLSV2.PgmState.IDLE
            assert con.make_directory("TNC:\\RUMBA")
            for name, text in {**job.files, "RUMBA.H": job.text}.items():
                (local / name).write_text(text)
                assert con.send_file(local / name, f"TNC:\\RUMBA\\{name}", override_file=True)
            info = con.file_info("TNC:\\RUMBA\\RUMBA.H")
            assert info is not None and info.size == len(job.text)
            assert not con.login(pyLSV2.Login.PLCDEBUG, "807667")  # refused by the TNC
            return con.versions.nc_sw, info.size, ""
        finally:
            con.disconnect()

    nc_sw, _, _ = await asyncio.to_thread(tncremo)
    assert nc_sw.startswith("340595")
    await fe.nc_start("TNC:\\RUMBA\\RUMBA.H")  # the operator
    await ctrl.wait_done(60)
    assert ctrl.state == "done"

    def read_back() -> tuple[int, str, str]:
        con = pyLSV2.LSV2("127.0.0.1", port=port, timeout=5, safe_mode=False)
        con.connect()
        try:
            con.login(pyLSV2.Login.DNC)
            state = con.program_status()
            stack = con.program_stack()
            assert con.recive_file("TNC:\\RUMBA\\RUMBA_RES.TXT", local / "res.txt", True)
            return int(state), stack.main, (local / "res.txt").read_text()
        finally:
            con.disconnect()

    state, main, text = await asyncio.to_thread(read_back)
    await fe.stop()
    assert state == pyLSV2.PgmState.FINISHED and main == "TNC:\\RUMBA\\RUMBA.H"
    hits = [DIALECT.parse_result(ln) for ln in text.splitlines() if ln.startswith("RUMBA")]
    assert [h.seq for h in hits] == list(range(1, job.touch_count + 1))
    for h, t in zip(hits, ctrl.touches, strict=True):  # F-PRINT's %.4LF: 0.05 µm steps
        assert all(abs(h.axes[k] - t.latched[k]) <= 0.5e-4 + 1e-12 for k in "XYZ")


async def test_link_runs_the_program_the_operator_starts_and_says_it_waits(truth):
    ctrl = VirtualController(truth, dialect="heidenhain")
    fe = Lsv2Frontend(ctrl, auto_start=None)
    port = await fe.start()
    link = Lsv2Link(cfg(port), dialect=DIALECT)
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
        assert "waiting for NC start" in steps[0] and ctrl.state == "idle" and not got
        assert {"RUMBA.H", "RUMBASTP.H", "RUMBAV.H"} <= {p.rpartition("\\")[2]
                                                          for p in fe.files}
        await fe.nc_start("TNC:\\RUMBA\\RUMBA.H")
        async with asyncio.timeout(60):
            await task
        latched_equal(got, ctrl, job, tol_mm=0.5e-4 + 1e-12)
        assert steps[-1] is None
        await link.write_verdict(Verdict("FAIL", "r"))
        assert ctrl.verdict == 3 and ctrl.variables["Q1598"] == 3.0  # RUMBAV.H called
    finally:
        task.cancel()
        await link.close()
        await fe.stop()


async def test_stop_program_ends_the_run_and_a_stop_before_start_holds(truth):
    # a TNC program does not wait for its reader (results go to a file): a real-time-ish
    # control, so that the stop lands while it runs (≈ 5 s of wall time for the program)
    ctrl = VirtualController(truth, dialect="heidenhain", time_scale=0.05)
    fe = Lsv2Frontend(ctrl, auto_start=None)
    port = await fe.start()
    link = Lsv2Link(cfg(port), dialect=DIALECT)
    await link.connect()
    try:
        agen = link.run(job_for(truth))
        first = asyncio.ensure_future(anext(agen))
        await until(lambda: "TNC:\\RUMBA\\RUMBA.H" in fe.files)
        await fe.nc_start("TNC:\\RUMBA\\RUMBA.H")
        assert (await first).seq == 1
        await link.abort()  # Q1689 = 1: the program ends at its next touch, no error
        # ... unless a touch called the stop program in the instant pylsv2 replaced it (it
        # deletes, then writes): the TNC then stops the program with an error — stopped too
        assert (ctrl.state == "done" and ctrl.alarm is None) or (
            ctrl.state == "alarm" and "RUMBASTP.H: program not found" in ctrl.alarm), \
            (ctrl.state, ctrl.alarm)
        with pytest.raises(LinkError, match="stop request"):
            async for _ in agen:
                pass
        agen = link.run(job_for(truth, poses=((0.0, 0.0),)))
        pending = asyncio.ensure_future(anext(agen))
        await until(lambda: fe.files.get("TNC:\\RUMBA\\RUMBASTP.H", b"").endswith(
            b"END PGM RUMBASTP MM\n") and b"+0" in fe.files["TNC:\\RUMBA\\RUMBASTP.H"])
        await asyncio.sleep(0.2)
        await link.abort()  # not started yet: the stop waits in RUMBASTP.H
        await fe.nc_start("TNC:\\RUMBA\\RUMBA.H")
        await ctrl.wait_done(30)
        assert ctrl.state == "done" and ctrl.touches == []  # ended before its first touch
        pending.cancel()
        await asyncio.gather(pending, return_exceptions=True)
    finally:
        await link.close()
        await fe.stop()


async def test_internal_stop_at_the_tnc_is_reported_as_cancelled_there(truth):
    ctrl = VirtualController(truth, dialect="heidenhain", time_scale=0.05)
    fe = Lsv2Frontend(ctrl)
    port = await fe.start()
    link = Lsv2Link(cfg(port), dialect=DIALECT)
    await link.connect()
    try:
        got = []
        with pytest.raises(ControllerAborted, match="cancelled on the TNC"):
            async for h in link.run(job_for(truth)):
                got.append(h)
                if len(got) == 2:
                    await ctrl.abort()
        assert [h.seq for h in got] == list(range(1, len(got) + 1))
    finally:
        await link.close()
        await fe.stop()


async def test_start_request_file_and_the_machine_filter(truth):
    ctrl = VirtualController(truth, dialect="heidenhain")
    fe = Lsv2Frontend(ctrl)
    port = await fe.start()
    fe.dirs.add("TNC:\\RUMBA")
    link = Lsv2Link(cfg(port, request_machine="OTHER"), dialect=DIALECT)
    await link.connect()
    try:
        waiting = asyncio.create_task(link.wait_start_request())
        ctrl.raise_start_request()  # names this machine, not OTHER: dropped
        await until(lambda: "TNC:\\RUMBA\\RUMBA_REQ.TXT" not in fe.files, 10)
        assert not waiting.done()
        waiting.cancel()
        await asyncio.gather(waiting, return_exceptions=True)
        link.cfg = cfg(port, request_machine=ctrl.machine_id.lower())
        ctrl.raise_start_request()
        async with asyncio.timeout(10):
            req = await link.wait_start_request()
        assert req.machine == ctrl.machine_id and "RUMBA_REQ.TXT" in req.detail
        assert "TNC:\\RUMBA\\RUMBA_REQ.TXT" not in fe.files  # consumed
    finally:
        await link.close()
        await fe.stop()


async def test_a_tnc_that_forbids_dnc_is_one_clear_error(truth):
    fe = Lsv2Frontend(VirtualController(truth, dialect="heidenhain"), dnc_allowed=False)
    port = await fe.start()
    try:
        with pytest.raises(LinkError, match="does not allow DNC"):
            await Lsv2Link(cfg(port), dialect=DIALECT).connect()
        with pytest.raises(LinkError, match="refused"):
            await Lsv2Link(cfg(1), dialect=DIALECT).connect()  # nothing listens there
    finally:
        await fe.stop()


async def test_config_errors_name_the_key():
    from contracts.yaml_files import ConfigError
    from drivers.registry import link_config

    base = {"transport": "lsv2", "host": "10.0.0.23"}
    for extra, match in (({"directory": "C:\\RUMBA"}, "TNC:"),
                         ({"directory": "TNC:\\rumba;x"}, "TNC:"), ({"port": 0}, "port"),
                         ({"password": "x"}, "password")):
        with pytest.raises(ConfigError, match=match):
            link_config({**base, **extra})


# ------------------------------------------------------------------------------ fuzz

class GarbageTnc(Lsv2Frontend):
    """The simulated TNC answering one kind of request with whatever it is given."""

    target = ""
    garbage = b""

    def _handle(self, conn, code, payload):
        if code == self.target:
            return self.garbage
        return super()._handle(conn, code, payload)


FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[
    HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def replies(draw_target: str) -> st.SearchStrategy[bytes]:
    """A reply to a request: a well-formed telegram of any command and payload, a length
    that lies, or raw bytes."""
    codes = st.sampled_from(["S_RI", "S_FI", "S_FL", "T_ER", "T_OK", "T_FD", "XXXX", "S_VR"])
    framed = st.builds(telegram, codes, st.binary(max_size=40))
    lying = st.builds(lambda c, n, p: struct.pack("!L", n) + c.encode() + p, codes,
                      st.integers(0, 2**32 - 1), st.binary(max_size=8))
    return st.one_of(framed, lying, st.binary(min_size=1, max_size=24))


@FUZZ
@given(st.sampled_from(["R_RI", "R_FI", "R_FL"]), st.data())
def test_garbage_from_the_tnc_is_a_clear_error_never_a_traceback_or_a_hang(target, data):
    """Whatever the TNC sends back for the program state, a file's info or a file's data, the
    link returns a valid value or raises LinkError within its timeout (tracebacks 0, hangs 0:
    each call bounded; a value of the wrong type is never accepted)."""
    garbage = data.draw(replies(target))

    async def one() -> None:
        truth = make_truth()
        fe = GarbageTnc(VirtualController(truth, dialect="heidenhain"))
        fe.target, fe.garbage = "", b""
        port = await fe.start()
        fe.dirs.add("TNC:\\RUMBA")
        fe.files["TNC:\\RUMBA\\RUMBA_RES.TXT"] = b"RUMBA 1 0 0 B1 1 1 1.0 2.0 3.0 0.0 0.0\n"
        link = Lsv2Link(cfg(port, timeout_s=0.5), dialect=DIALECT)
        try:
            await link.connect()
            fe.target, fe.garbage = target, garbage
            t0 = time.monotonic()
            try:
                if target == "R_RI":
                    state = await link._s.program_state()
                    assert isinstance(state, int) and 0 <= state <= 8
                elif target == "R_FI":
                    size = await link._s.exists("TNC:\\RUMBA\\RUMBA_RES.TXT")
                    assert size is None or (isinstance(size, int) and size >= 0)
                else:
                    text = await link._s.get("TNC:\\RUMBA\\RUMBA_RES.TXT")
                    assert isinstance(text, str)
            except LinkError:
                pass
            assert time.monotonic() - t0 < 10  # bounded by the telegram timeout
        finally:
            await link.close()
            link._s.shutdown()
            await fe.stop()

    asyncio.run(one())


lines = st.one_of(
    st.text(max_size=80),
    st.builds(lambda seq, vals: f"RUMBA {seq} 0 0 B1 1 1 " + " ".join(vals), st.integers(0, 3),
              st.lists(st.sampled_from(["1.0", "nan", "1e999", "-2.5", "x", "1e6"]),
                       min_size=0, max_size=6)))


@settings(max_examples=300, deadline=None)
@given(lines)
def test_garbage_in_the_result_file_is_a_hit_or_a_clear_error(line):
    """A line of RUMBA_RES.TXT: touch 1 with plausible values, None (other output), or a
    LinkError / MalformedResult — never another exception, never touch 2 first."""
    job = ProgramJob(run_id="f", text="", dialect="heidenhain", touch_count=5,
                     touches=TouchTable(TouchId(seq=k, pose=0, ball="B1", touch=k)
                                        for k in range(1, 6)))
    hits = HitFactory(job)
    try:
        hit = Lsv2Link._decode(DIALECT, hits, line)
    except (LinkError, MalformedResult):
        return
    if hit is not None:
        assert hit.seq == 1 and hits.made == 1
        assert all(abs(v) <= 1e5 for v in hit.axes.values())


def test_only_the_stop_and_verdict_codes_reach_their_programs():
    from drivers.lsv2.link import NO_VERDICT, stop_program

    assert stop_program(True).splitlines()[1] == "1 Q1689 = +1"
    assert stop_program(False).splitlines()[1] == "1 Q1689 = +0"
    assert NO_VERDICT.splitlines()[1] == "1 Q1598 = +0"
    with pytest.raises(ValueError):
        DIALECT.verdict_program("1; FN 14: ERROR = 1")  # type: ignore[arg-type]
