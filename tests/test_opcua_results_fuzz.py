"""Fuzz of the OPC UA results server's methods through a real asyncua client (SignAndEncrypt,
user and password), the server on its own event loop in a thread with a loop-lag monitor, the
client on another: filters of random shape and depth (random elements, operators and operands;
well-formed trees checked against an oracle; doubly referenced chains up to depth 30), result
ids, random arguments to every method, report files with random handles and sequences of Read /
GetPosition / SetPosition / Close, some never closed. Counted: server tracebacks and
BadUnexpectedError / BadInternalError answers (0), wrong filter answers (0), loop stalls over
0.2 s (0), handles left once the clients' sessions are gone (0)."""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from asyncua import ua
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon.opcua import filetransfer, results
from daemon.opcua.filters import FIELDS
from daemon.store.journal import Store
from tests.opcua_bounds_helpers import (
    REPORTED,
    Nodes,
    Tracebacks,
    client,
    doubled_chain,
    filtered_args,
    need_nodesets,
    options,
    secure,
)
from tests.stop_helpers import ROOT

EXAMPLES = 1200
RUNS = 200  # journal runs besides the six cases: a filter has rows to work through
SC = ua.StatusCodes
DEFECTS = {SC.BadUnexpectedError, SC.BadInternalError}
VT = ua.VariantType


class LoopThread:
    """An event loop running in its own thread; ``run`` executes a coroutine there."""

    def __init__(self, name: str) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name=name, daemon=True)
        self.thread.start()

    def run(self, coro: Any, timeout_s: float = 120.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(30)
        self.loop.close()


class Harness:
    """The server's process (tests/opcua_fuzz_server.py), the client's thread, the tallies."""

    def __init__(self, tmp: Path) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "tests.opcua_fuzz_server", str(tmp),
                                      str(RUNS)], cwd=ROOT, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        first = self.proc.stdout.readline()
        assert first, f"the fuzz server ended ({self.proc.wait()})"
        info = json.loads(first)
        self.served = SimpleNamespace(url=info["url"], pki={"cert": Path(info["cert"]),
                                                           "key": Path(info["key"])})
        self.rows = self._rows(Path(info["db"]))
        self.cli_thread = LoopThread("opcua-client")
        self.client: Any = None
        self.nodes: Nodes | None = None
        self.counts: Counter[str] = Counter()
        self.statuses: Counter[str] = Counter()
        self.reconnect()

    @staticmethod
    def _rows(db: Path) -> list[dict[str, Any]]:
        """Each run's filter fields, as the server sees them (the oracle's input)."""
        store = Store(db)
        try:
            out = []
            for run in store.runs("mill1", results.MAX_RUNS):
                v = store.verdict(run.id) if run.verdict else None
                out.append(results.row_of(run, v["checks"] if v else None))
            return out
        finally:
            store.close()

    def stats(self) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write("stats\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def reconnect(self) -> None:
        async def go() -> tuple[Any, Nodes]:
            if self.client is not None:
                await self.client.disconnect()
            c = await secure(client(self.served), self.served)  # type: ignore[arg-type]
            await c.connect()
            return c, await Nodes.of(c)
        self.client, self.nodes = self.cli_thread.run(go())

    def call(self, obj: str, name: str, *args: ua.Variant, node: Any = None) -> Any:
        n = self.nodes
        assert n is not None
        target = node if node is not None else getattr(n, obj)
        r = self.cli_thread.run(n.call(target, name, *args))
        self.counts["calls"] += 1
        self.statuses[ua.StatusCode(r.StatusCode.value).name] += 1
        if r.StatusCode.value in DEFECTS:
            self.counts["defect answers"] += 1
        return r

    def close(self) -> dict[str, Any]:
        """Disconnect; once the server swept the session's files, its figures."""
        async def bye() -> None:
            await self.client.disconnect()

        try:
            self.cli_thread.run(bye())
            deadline = time.monotonic() + 4 * filetransfer.SWEEP_S + 10
            while (st := self.stats())["open"] and time.monotonic() < deadline:
                time.sleep(0.1)
        finally:
            self.cli_thread.close()
            assert self.proc.stdin is not None
            self.proc.stdin.write("quit\n")
            self.proc.stdin.close()
            self.proc.wait(60)
        return {"leaked handles": st["open"], "loop wake-ups": st["wakeups"],
                "stalls over 0.2 s": st["stalls"], "worst loop lag s": round(st["worst_s"], 3),
                "worst loop CPU s": round(st["worst_cpu_s"], 3),
                "released without Close": st["released"], "server tracebacks": st["tracebacks"]}


# ------------------------------------------------------------------------------- strategies
INT32 = st.integers(-(2**31), 2**31 - 1)
LITERALS = st.one_of(
    INT32.map(lambda v: ua.Variant(v, VT.Int32)),
    st.integers(0, 4).map(lambda v: ua.Variant(v, VT.Int32)),
    st.floats(allow_nan=True, allow_infinity=True).map(lambda v: ua.Variant(v, VT.Double)),
    st.text(max_size=24).map(lambda v: ua.Variant(v, VT.String)),
    st.sampled_from(["run-pass", "run-fail", "bulk-00007", "thesis-4ball"]).map(ua.Variant),
    st.booleans().map(lambda v: ua.Variant(v, VT.Boolean)),
    st.datetimes(min_value=dt.datetime(1990, 1, 1), max_value=dt.datetime(2100, 1, 1),
                 timezones=st.just(dt.UTC)).map(lambda v: ua.Variant(v, VT.DateTime)),
    st.binary(max_size=8).map(lambda v: ua.Variant(v, VT.ByteString)),
    st.lists(st.integers(0, 5), max_size=3).map(lambda v: ua.Variant(v, VT.Int32)),
    st.just(ua.Variant(None)),
)
NAMES = st.one_of(st.sampled_from(sorted(FIELDS)), st.text(max_size=16))


def _attribute(res: int) -> Any:
    return st.builds(
        lambda path: ua.SimpleAttributeOperand(BrowsePath=path,
                                               AttributeId=ua.AttributeIds.Value),
        st.lists(NAMES.map(lambda n: ua.QualifiedName(n, res)), max_size=3))


def _operand(res: int, n: int) -> Any:
    return st.one_of(
        LITERALS.map(lambda v: ua.LiteralOperand(Value=v)),
        _attribute(res),
        st.one_of(st.integers(0, n + 2), st.just(2**32 - 1)).map(
            lambda i: ua.ElementOperand(Index=i)),
        st.just(ua.AttributeOperand(NodeId=ua.NodeId(1), Alias="x",
                                    AttributeId=ua.AttributeIds.Value)))


def random_filter(res: int) -> Any:
    """Any shape: random operators and operands, references anywhere (cycles, out of range)."""
    return st.integers(0, 70).flatmap(lambda n: st.lists(st.builds(
        lambda op, ops: ua.ContentFilterElement(FilterOperator=op, FilterOperands=ops),
        st.sampled_from(list(ua.FilterOperator)),
        st.lists(_operand(res, n), max_size=3)), min_size=n, max_size=n)).map(
        lambda els: ("random", ua.ContentFilter(Elements=els)))


def _leaf() -> Any:
    cmp = st.sampled_from([ua.FilterOperator.Equals, ua.FilterOperator.GreaterThan,
                           ua.FilterOperator.LessThan, ua.FilterOperator.GreaterThanOrEqual,
                           ua.FilterOperator.LessThanOrEqual])
    value = {"ResultState": st.integers(0, 5), "ResultEvaluation": st.integers(0, 3),
             "ResultId": st.sampled_from(["run-pass", "run-nd", "bulk-00010", "zzz", ""]),
             "JobId": st.sampled_from(["run-fail", "bulk-00150", "a"]),
             "PartId": st.sampled_from(["thesis-4ball", "", "x"]),
             "CreationTime": st.datetimes(min_value=dt.datetime(2020, 1, 1),
                                          max_value=dt.datetime(2030, 1, 1),
                                          timezones=st.just(dt.UTC))}
    return st.sampled_from(sorted(value)).flatmap(
        lambda f: st.tuples(cmp, st.just(f), value[f]))


TREES = st.recursive(_leaf(), lambda sub: st.one_of(
    st.tuples(st.sampled_from([ua.FilterOperator.And, ua.FilterOperator.Or]), sub, sub),
    st.tuples(st.just(ua.FilterOperator.Not), sub)), max_leaves=12)


def _flatten(tree: tuple, res: int) -> list[ua.ContentFilterElement]:
    """A tree as ContentFilter elements: each node before the nodes it uses."""
    out: list[Any] = []

    def put(t: tuple) -> int:
        i = len(out)
        out.append(None)
        if t[0] in (ua.FilterOperator.And, ua.FilterOperator.Or, ua.FilterOperator.Not):
            ops = [ua.ElementOperand(Index=put(s)) for s in t[1:]]
        else:
            ops = [ua.SimpleAttributeOperand(BrowsePath=[
                ua.QualifiedName("ResultMetaData", res), ua.QualifiedName(t[1], res)],
                AttributeId=ua.AttributeIds.Value), ua.LiteralOperand(Value=ua.Variant(t[2]))]
        out[i] = ua.ContentFilterElement(FilterOperator=t[0], FilterOperands=ops)
        return i
    put(tree)
    return out


def oracle(tree: tuple, row: dict[str, Any]) -> bool:
    op = tree[0]
    if op == ua.FilterOperator.And:
        return oracle(tree[1], row) and oracle(tree[2], row)
    if op == ua.FilterOperator.Or:
        return oracle(tree[1], row) or oracle(tree[2], row)
    if op == ua.FilterOperator.Not:
        return not oracle(tree[1], row)
    a, b = row[tree[1]], tree[2]
    if a is None:
        return False
    return {ua.FilterOperator.Equals: a == b, ua.FilterOperator.GreaterThan: a > b,
            ua.FilterOperator.LessThan: a < b, ua.FilterOperator.GreaterThanOrEqual: a >= b,
            ua.FilterOperator.LessThanOrEqual: a <= b}[op]


def _variant() -> Any:
    return st.one_of(LITERALS, st.integers(0, 2**32 - 1).map(lambda v: ua.Variant(v, VT.UInt32)),
                     st.just(ua.Variant(ua.ContentFilter(), VT.ExtensionObject)),
                     st.just(ua.Variant([], VT.ExtensionObject)))


METHODS = ["GetLatestResult", "GetResultById", "GetResultIdListFiltered",
           "ReleaseResultHandle", "AcknowledgeResults"]
FILE_OPS = st.lists(st.tuples(st.sampled_from(["0:Read", "0:GetPosition", "0:SetPosition",
                                               "0:Close", "0:Open"]),
                              st.booleans(),  # the real handle, or a random one
                              st.integers(-(2**31), 2**31 - 1)), max_size=6)


def actions(res: int) -> Any:
    return st.one_of(
        random_filter(res),
        st.tuples(st.just("tree"), TREES, st.integers(0, 5)),
        st.integers(1, 30).map(lambda d: ("deep", d)),
        st.tuples(st.just("id"), st.one_of(st.text(max_size=80), st.sampled_from(
            ["run-pass", "run-nd", "bulk-00001", "../x", "", "run-aborted"]))),
        st.tuples(st.just("call"), st.sampled_from([*METHODS, "0:GenerateFileForRead"]),
                  st.lists(_variant(), max_size=5)),
        st.tuples(st.just("file"), st.sampled_from([REPORTED, REPORTED, "run-fail", "nope"]),
                  FILE_OPS),
    )


def do(h: Harness, action: tuple) -> None:
    n = h.nodes
    assert n is not None
    kind = action[0]
    h.counts[kind] += 1
    if kind in ("random", "deep", "tree"):
        if kind == "random":
            flt, top = action[1], 0
        elif kind == "deep":
            flt, top = doubled_chain(action[1], n.res), 0
        else:
            flt, top = ua.ContentFilter(Elements=_flatten(action[1], n.res)), action[2]
        r = h.call("rm", "GetResultIdListFiltered", *filtered_args(flt, top))
        assert r.StatusCode.is_good(), r.StatusCode
        ids, err = r.OutputArguments[1], r.OutputArguments[2]
        assert err in (0, results.ERR_FILTER) and (err == 0 or ids == [])
        h.counts[f"filter answered {err}"] += 1
        if kind == "tree":
            want = [row["ResultId"] for row in h.rows if oracle(action[1], row)]
            if ids != (want[:top] if top else want) or err != 0:
                h.counts["wrong filter answers"] += 1
        if kind == "deep" and action[1] <= 16 and err != 0:
            h.counts["wrong filter answers"] += 1
    elif kind == "id":
        r = h.call("rm", "GetResultById", ua.Variant(action[1], VT.String),
                   ua.Variant(1000, VT.Int32))
        assert r.StatusCode.is_good(), r.StatusCode
        known = any(row["ResultId"] == action[1] for row in h.rows)
        assert (r.OutputArguments[2] == 0) == known, (action, r.OutputArguments[2])
    elif kind == "call":
        obj = "transfer" if action[1].startswith("0:") else "rm"
        h.call(obj, action[1], *action[2])
    else:
        _file(h, action[1], action[2])


def _file(h: Harness, run_id: str, ops: list) -> None:
    n = h.nodes
    assert n is not None
    g = h.call("transfer", "0:GenerateFileForRead", options(run_id, n.res))
    if not g.StatusCode.is_good():
        assert g.StatusCode.value in (SC.BadNotFound, SC.BadTooManyOperations), g.StatusCode
        return
    node = h.client.get_node(g.OutputArguments[0])
    handle = g.OutputArguments[1]
    for name, real, number in ops:
        hv = ua.Variant(handle if real else number % 2**32, VT.UInt32)
        if name == "0:Read":
            h.call("", name, hv, ua.Variant(number, VT.Int32), node=node)
        elif name == "0:SetPosition":
            h.call("", name, hv, ua.Variant(abs(number), VT.UInt64), node=node)
        elif name == "0:Open":
            h.call("", name, ua.Variant(number % 256, VT.Byte), node=node)
        else:
            r = h.call("", name, hv, node=node)
            if name == "0:Close" and r.StatusCode.is_good():
                return


@pytest.mark.slow
def test_the_results_servers_methods_survive_a_fuzz(tmp_path):
    need_nodesets()
    h = Harness(tmp_path)
    res = h.nodes.res  # type: ignore[union-attr]
    done = 0
    with Tracebacks() as tb:
        try:
            @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                      suppress_health_check=list(HealthCheck))
            @given(action=actions(res))
            def one(action: tuple) -> None:
                nonlocal done
                done += 1
                if done % 150 == 0:  # a new session: the last one's files go with it
                    h.reconnect()
                do(h, action)

            one()
        finally:
            figures = h.close()
    figures.update(h.counts)
    print("fuzz figures:", dict(sorted(figures.items())))
    print("answers:", dict(h.statuses.most_common()))
    assert done >= 1000 and h.counts["calls"] >= 1000, figures
    assert figures["server tracebacks"] == [], figures["server tracebacks"][:3]
    assert tb.records == [], tb.lines()[:3]  # nor in this process (the client's)
    assert h.counts["defect answers"] == 0, h.statuses
    assert h.counts["wrong filter answers"] == 0, figures
    assert figures["stalls over 0.2 s"] == 0, figures
    assert figures["leaked handles"] == 0, figures
