"""The OPC UA results server's bounds, through a real asyncua client over SignAndEncrypt: a
deep filter from an authenticated client answers at once without stalling the daemon's loop (a
doubly referenced chain was 2^depth evaluations per run, on the loop); cyclic, malformed and
unsupported filters answer −3; calls with missing or wrong arguments answer the Call service's
status codes (asyncua's BadUnexpectedError and a logged traceback before); report files a
client leaves open are released with its session, at most four per session; wrong passwords
are locked out as at the HMI."""

from __future__ import annotations

import asyncio
import time

import pytest
import pytest_asyncio
from asyncua import ua

from benchmarks.rigs.opcua_results_helpers import PASSWORD
from daemon.opcua import filetransfer
from daemon.opcua.filters import MAX_DEPTH
from tests.opcua_bounds_helpers import (
    REPORTED,
    LagMonitor,
    Nodes,
    Tracebacks,
    client,
    doubled_chain,
    field_operand,
    filtered_args,
    options,
    secure,
    serve,
    until,
)

SC = ua.StatusCodes
pytestmark = pytest.mark.asyncio(loop_scope="module")


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def served(tmp_path_factory):
    s = await serve(tmp_path_factory.mktemp("bounds"))
    yield s
    await s.close()


@pytest_asyncio.fixture(loop_scope="module")
async def session(served):
    c = await secure(client(served), served)
    async with c:
        yield c, await Nodes.of(c)


async def test_a_deep_filter_neither_stalls_the_loop_nor_is_followed_twice(served, session):
    _c, n = session
    monitor = LagMonitor().start()
    with Tracebacks() as tb:
        for depth in (MAX_DEPTH, 18, 22):
            r = await n.call(n.rm, "GetResultIdListFiltered",
                             *filtered_args(doubled_chain(depth, n.res)))
            assert r.StatusCode.is_good(), r.StatusCode
            ids, err = r.OutputArguments[1], r.OutputArguments[2]
            if depth <= MAX_DEPTH:  # evaluated: the runs completed (ResultState 1)
                assert err == 0 and ids == ["run-warn", "run-nd", "run-fail", "run-pass"]
            else:
                assert (ids, err) == ([], -3)
    await asyncio.sleep(0.1)
    await monitor.stop()
    assert monitor.wakeups > 0 and monitor.stalls == 0, monitor
    assert tb.records == [], tb.lines()


def _el(op: ua.FilterOperator, *operands: object) -> ua.ContentFilterElement:
    return ua.ContentFilterElement(FilterOperator=op, FilterOperands=list(operands))


@pytest.mark.parametrize("case", ["cycle", "self", "backward", "not-without-operand",
                                  "and-one-operand", "out-of-range", "unsupported-operator",
                                  "string-vs-number", "array-literal", "too-many-elements"])
async def test_a_malformed_filter_answers_minus_3(served, session, case):
    _c, n = session
    rs = field_operand("ResultState", n.res)
    one = ua.LiteralOperand(Value=ua.Variant(1))
    eq = _el(ua.FilterOperator.Equals, rs, one)
    els = {
        "cycle": [_el(ua.FilterOperator.And, ua.ElementOperand(Index=1), ua.ElementOperand(
            Index=1)), _el(ua.FilterOperator.Or, ua.ElementOperand(Index=0),
                           ua.ElementOperand(Index=0))],
        "self": [_el(ua.FilterOperator.Not, ua.ElementOperand(Index=0))],
        "backward": [eq, _el(ua.FilterOperator.Not, ua.ElementOperand(Index=0))],
        "not-without-operand": [_el(ua.FilterOperator.Not)],
        "and-one-operand": [_el(ua.FilterOperator.And, ua.ElementOperand(Index=1)), eq],
        "out-of-range": [_el(ua.FilterOperator.Not, ua.ElementOperand(Index=7))],
        "unsupported-operator": [_el(ua.FilterOperator.Like, rs, one)],
        "string-vs-number": [_el(ua.FilterOperator.Equals, field_operand("ResultId", n.res),
                                 one)],
        "array-literal": [_el(ua.FilterOperator.Equals, rs,
                              ua.LiteralOperand(Value=ua.Variant([1, 2])))],
        "too-many-elements": [_el(ua.FilterOperator.Not, ua.ElementOperand(Index=k + 1))
                              for k in range(80)] + [eq],
    }[case]
    with Tracebacks() as tb:
        r = await n.call(n.rm, "GetResultIdListFiltered",
                         *filtered_args(ua.ContentFilter(Elements=els)))
    assert r.StatusCode.is_good(), r.StatusCode
    assert (r.OutputArguments[1], r.OutputArguments[2]) == ([], -3)
    assert tb.records == [], tb.lines()


@pytest.mark.parametrize(("method", "args", "status"), [
    ("GetResultById", (), SC.BadArgumentsMissing),
    ("GetResultById", (ua.Variant("run-pass"),), SC.BadArgumentsMissing),
    ("GetResultById", (ua.Variant(5), ua.Variant(1000)), SC.BadInvalidArgument),
    ("GetResultById", (ua.Variant("run-pass"), ua.Variant(1000), ua.Variant(1)),
     SC.BadTooManyArguments),
    ("GetLatestResult", (), SC.BadArgumentsMissing),
    ("GetLatestResult", (ua.Variant("soon"),), SC.BadInvalidArgument),
    ("GetResultIdListFiltered", (ua.Variant(3),), SC.BadArgumentsMissing),
    ("GetResultIdListFiltered", (ua.Variant("x"), ua.Variant(None), ua.Variant(0),
                                 ua.Variant(0)), SC.BadInvalidArgument),
    ("GetResultIdListFiltered", (ua.Variant(None), ua.Variant(None), ua.Variant(-1),
                                 ua.Variant(0)), SC.BadInvalidArgument),
    ("ReleaseResultHandle", (ua.Variant("h"),), SC.BadInvalidArgument),
    ("AcknowledgeResults", (ua.Variant(7),), SC.BadInvalidArgument),
    ("AcknowledgeResults", (), SC.BadArgumentsMissing),
])
async def test_a_call_with_missing_or_wrong_arguments_answers_its_status(
        served, session, method, args, status):
    _c, n = session
    with Tracebacks() as tb:
        r = await n.call(n.rm, method, *args)
    assert r.StatusCode.value == status, (r.StatusCode, ua.StatusCode(status))
    assert tb.records == [], tb.lines()


async def test_results_by_id_still_answer(served, session):
    _c, n = session
    r = await n.call(n.rm, "GetResultById", ua.Variant("run-fail"),
                     ua.Variant(1000.0, ua.VariantType.Double))
    assert r.StatusCode.is_good() and r.OutputArguments[2] == 0
    assert r.OutputArguments[1].ResultMetaData.ResultId == "run-fail"
    r = await n.call(n.rm, "GetResultIdListFiltered", ua.Variant(None), ua.Variant(None),
                     ua.Variant(2, ua.VariantType.UInt32), ua.Variant(1000))
    assert r.StatusCode.is_good() and r.OutputArguments[1:] == [["run-aborted", "run-warn"], 0]


async def test_files_left_open_are_released_with_the_session_and_limited_per_session(served):
    transfer = served.srv.machines["mill1"].transfer
    assert transfer.open == {}
    nodes = served.srv.server.iserver.aspace._nodes
    before = len(nodes)
    c = await secure(client(served), served)
    await c.connect()
    n = await Nodes.of(c)
    got = [await n.call(n.transfer, "0:GenerateFileForRead", options(REPORTED, n.res))
           for _ in range(filetransfer.MAX_PER_SESSION + 1)]
    assert [g.StatusCode.is_good() for g in got] == [True] * filetransfer.MAX_PER_SESSION + [
        False]
    assert got[-1].StatusCode.value == SC.BadTooManyOperations
    assert len(transfer.open) == filetransfer.MAX_PER_SESSION
    # another session is not locked out by the first one's files, nor can it use them
    other = await secure(client(served), served)
    async with other:
        m = await Nodes.of(other)
        mine = await m.call(m.transfer, "0:GenerateFileForRead", options(REPORTED, m.res))
        assert mine.StatusCode.is_good()
        node, handle = got[0].OutputArguments[0], got[0].OutputArguments[1]
        stolen = await m.call(other.get_node(node), "0:Read",
                              ua.Variant(handle, ua.VariantType.UInt32),
                              ua.Variant(100, ua.VariantType.Int32))
        assert stolen.StatusCode.value == SC.BadInvalidArgument
        closed = await m.call(other.get_node(mine.OutputArguments[0]), "0:Close",
                              ua.Variant(mine.OutputArguments[1], ua.VariantType.UInt32))
        assert closed.StatusCode.is_good()
    # the client goes away without Close: its session ends, its files are released
    await c.disconnect()
    await until(lambda: transfer.open == {}, timeout_s=4 * filetransfer.SWEEP_S + 10)
    # the file objects are gone from the address space, and no reference points to them
    assert len(nodes) == before
    assert [r for n in nodes.values() for r in n.references if r.NodeId not in nodes] == []


async def test_wrong_passwords_are_locked_out_before_the_password_is_compared(tmp_path):
    s = await serve(tmp_path)
    try:
        refused = 0
        for _ in range(5):
            c = await secure(client(s, password="wrong-password-guess"), s)
            with pytest.raises(ua.UaStatusCodeError):
                await c.connect()
            refused += 1
            await c.disconnect()
        # the fifth wrong one locked this address out: now even the right password is refused
        c = await secure(client(s, password=PASSWORD), s)
        with pytest.raises(ua.UaStatusCodeError) as e:
            await c.connect()
        await c.disconnect()
        assert e.value.code == SC.BadUserAccessDenied and refused == 5
        limiter = s.srv.server.iserver.user_manager.limiter
        assert limiter.retry_after("127.0.0.1") > 0
    finally:
        await s.close()


async def test_the_lag_monitor_counts_computing_on_the_loop_not_waiting_for_a_core():
    monitor = LagMonitor().start()
    await asyncio.sleep(0.05)
    t = time.thread_time()
    while time.thread_time() - t < 0.3:  # a method computing on the loop for 0.3 CPU s
        pass
    await asyncio.sleep(0.05)
    time.sleep(0.3)  # the loop's thread not computing (what a starved box looks like)
    await asyncio.sleep(0.05)
    await monitor.stop()
    assert monitor.stalls == 1 and monitor.worst_cpu_s >= 0.3, monitor
    # the clock saw both: a wake-up late by the 0.3 s less the part of its 20 ms period that
    # had run before the stall began
    assert monitor.worst_s >= 0.3 - monitor.period_s, monitor
