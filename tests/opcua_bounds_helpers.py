"""Set-up of the results server's bound tests (tests/test_opcua_results_bounds.py and the
fuzz): a journal with a report to download, the server, an authenticated asyncua client, a
loop-lag monitor, and a log handler that keeps every record carrying a traceback."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua

from benchmarks.rigs.opcua_results_helpers import (
    CLIENT_URI,
    NODESETS_DIR,
    PASSWORD,
    USER,
    fill,
    make_pki,
    server_config,
)
from daemon.opcua.server import ResultServer
from daemon.service.heap import freeze_startup_heap
from daemon.store.journal import Store

RESULT_URI = "http://opcfoundation.org/UA/Machinery/Result/"
RUMBA_URI = "urn:rumba-cnc:results"
REPORTED = "run-pass"  # the run with a report (HTML + PDF)


def need_nodesets() -> None:
    if not NODESETS_DIR.is_dir():
        pytest.skip("node-opcua-nodesets not installed (bash .ci/install-peers.sh node-opcua)")


@dataclass
class LagMonitor:
    """Counts how often the event loop came back late from a short sleep because it computed:
    a stall of the loop (a method computing on it) shows as one late wake-up, however long it
    lasted. A stall is counted by the CPU seconds the loop's thread spent between two wake-ups
    (``time.thread_time``), not by the clock: on a starved CI box the loop waits for a core
    without computing (2 wake-ups 0.2 s late on the wall clock in a loaded run, none of them
    the server's work), while a method computing on the loop spends its CPU there on any box.
    The wall-clock lag is kept as information (``worst_s``)."""

    period_s: float = 0.02
    stall_s: float = 0.2
    wakeups: int = 0
    stalls: int = 0
    worst_s: float = 0.0
    worst_cpu_s: float = 0.0
    stalled_at: list[tuple[float, float]] = field(default_factory=list)  # (loop time, CPU s)
    _task: asyncio.Task | None = None

    def start(self) -> LagMonitor:
        self._task = asyncio.get_running_loop().create_task(self._run())
        return self

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            t, cpu = loop.time(), time.thread_time()
            await asyncio.sleep(self.period_s)
            late = loop.time() - t - self.period_s
            busy = time.thread_time() - cpu
            self.wakeups += 1
            self.worst_s = max(self.worst_s, late)
            self.worst_cpu_s = max(self.worst_cpu_s, busy)
            if busy > self.stall_s:
                self.stalls += 1
                self.stalled_at.append((loop.time(), busy))

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task


class Tracebacks(logging.Handler):
    """Log records that carry a traceback (asyncua logs one for a method that raised)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info or "Traceback" in record.getMessage():
            self.records.append(record)

    def __enter__(self) -> Tracebacks:
        logging.getLogger().addHandler(self)
        return self

    def __exit__(self, *exc: Any) -> None:
        logging.getLogger().removeHandler(self)

    def lines(self) -> list[str]:
        return [f"{r.name}: {r.getMessage()[:200]}" for r in self.records]


@dataclass
class Served:
    srv: ResultServer
    store: Store
    url: str
    pki: dict[str, Path]
    tmp: Path
    extra: dict[str, Any] = field(default_factory=dict)

    async def close(self) -> None:
        await self.srv.stop()
        self.store.close()


async def serve(tmp: Path, extra_runs: int = 0) -> Served:
    """The server on a journal of the test cases (and ``extra_runs`` more), with a report."""
    need_nodesets()
    store = Store(tmp / "journal.sqlite")
    fill(store, extra=extra_runs)
    html = tmp / "reports" / f"{REPORTED}.html"
    html.parent.mkdir(exist_ok=True)
    html.write_text("<html>report</html>", encoding="utf-8")
    html.with_suffix(".pdf").write_bytes(b"%PDF-1.4\n" + os.urandom(100_000))
    store.save_report(REPORTED, html, html.with_suffix(".json"))
    cert, key, pem = await make_pki(tmp)
    srv = ResultServer(server_config(tmp, cert.parent), store, ["mill1"])
    url = await srv.start()
    freeze_startup_heap()  # as rumba run does once it serves
    return Served(srv, store, url, {"cert": cert, "key": key, "pem": pem}, tmp)


def client(served: Served, password: str = PASSWORD) -> Client:
    c = Client(served.url, timeout=30)
    c.application_uri = CLIENT_URI
    c.set_user(USER)
    c.set_password(password)
    return c


async def secure(c: Client, served: Served) -> Client:
    await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{served.pki['cert']},"
                                f"{served.pki['key']}")
    return c


@dataclass
class Nodes:
    """The nodes a test calls, found by browse name in the client's namespace indexes."""

    rm: Any
    transfer: Any
    res: int
    idx: int

    @classmethod
    async def of(cls, c: Client) -> Nodes:
        ns = await c.get_namespace_array()
        res, idx = ns.index(RESULT_URI), ns.index(RUMBA_URI)
        rm = c.get_node(ua.NodeId("mill1.ResultManagement", idx))
        return cls(rm, await rm.get_child([f"{res}:ResultTransfer"]), res, idx)

    async def call(self, obj: Any, name: str, *args: ua.Variant) -> ua.CallMethodResult:
        """One Call as a client sends it (``name`` in the Result namespace unless it says
        ``ns:``); the raw result, never raised: its status, its outputs' values."""
        method = await obj.get_child([name if ":" in name else f"{self.res}:{name}"])
        req = ua.CallMethodRequest(ObjectId=obj.nodeid, MethodId=method.nodeid,
                                   InputArguments=list(args))
        res = (await obj.session.call([req]))[0]
        res.OutputArguments = [v.Value for v in res.OutputArguments or []]
        return res


def options(run_id: str, res: int) -> ua.Variant:
    """ResultTransferOptions{ResultId} as OPC 10000-6 encodes it (an ExtensionObject whose
    body is the string)."""
    body = len(run_id.encode()).to_bytes(4, "little", signed=True) + run_id.encode()
    return ua.Variant(ua.ExtensionObject(TypeId=ua.NodeId(5001, res), Body=body),
                      ua.VariantType.ExtensionObject)


def field_operand(name: str, res: int) -> ua.SimpleAttributeOperand:
    return ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName("ResultMetaData", res),
                                                 ua.QualifiedName(name, res)],
                                     AttributeId=ua.AttributeIds.Value)


def doubled_chain(depth: int, res: int) -> ua.ContentFilter:
    """Elements 0 … depth-2 each And(next, next), the last ResultState = 1: 2^depth
    evaluations per run when followed recursively, ``depth`` with each element once."""
    els = [ua.ContentFilterElement(FilterOperator=ua.FilterOperator.And, FilterOperands=[
        ua.ElementOperand(Index=i + 1), ua.ElementOperand(Index=i + 1)])
        for i in range(depth - 1)]
    els.append(ua.ContentFilterElement(FilterOperator=ua.FilterOperator.Equals, FilterOperands=[
        field_operand("ResultState", res), ua.LiteralOperand(Value=ua.Variant(1))]))
    return ua.ContentFilter(Elements=els)


def filtered_args(flt: Any, max_results: int = 0) -> tuple[ua.Variant, ...]:
    return (ua.Variant(flt, ua.VariantType.ExtensionObject),
            ua.Variant([], ua.VariantType.ExtensionObject),
            ua.Variant(max_results, ua.VariantType.UInt32),
            ua.Variant(1000, ua.VariantType.Int32))


async def until(cond: Any, timeout_s: float = 30.0) -> None:
    """Wait until ``cond()`` holds (polled; fails after ``timeout_s``, a safety net)."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "condition not reached"
        await asyncio.sleep(0.05)
