"""An abort's cancellation that lands with an OPC UA response is not lost (drivers/cancel.py
``keep_cancel`` around every request of the OPC UA link). Python 3.11's ``asyncio.wait_for``
returns the response instead of raising when both land in one loop step (CPython gh-86296; the
Modbus link lost a daemon stop to it). asyncua 2.1 waits for a response with wait_for2, which
raises there; the link does not rest on that: with asyncio's own ``wait_for`` in asyncua's
place, a read, a write, a method call and a whole capturing run still end cancelled. Real
asyncua client against the simulator's asyncua server; the cancel is issued from the client's
response callback, in the very step the response is handed over."""

from __future__ import annotations

import asyncio
import sys

import pytest

from benchmarks.rigs.transport_sim import make_job
from simulators.controller import VirtualController
from tests.opcua_helpers import opcua_link, thesis_truth

WAITS = ["asyncua", pytest.param("asyncio", marks=pytest.mark.skipif(
    sys.version_info >= (3, 12), reason="CPython gh-86296 is fixed in 3.12"))]


class CancelWithResponse:
    """Cancels ``task`` from inside the client's response callback, right after the response
    future got its result: both land in one loop step."""

    def __init__(self, link, monkeypatch, wait: str) -> None:
        import asyncua.client.ua_client as ua_client

        if wait == "asyncio":  # the library waiting as Python 3.11's wait_for does
            monkeypatch.setattr(ua_client, "wait_for", asyncio.wait_for)
        proto = link._client.uaclient.protocol
        self.task: asyncio.Task | None = None
        self.fired = 0
        original = proto._call_callback

        def callback(request_id, body) -> None:
            original(request_id, body)
            if self.task is not None and not self.task.done():
                self.task.cancel()
                self.task, self.fired = None, self.fired + 1
        monkeypatch.setattr(proto, "_call_callback", callback)

    def arm(self, task: asyncio.Task) -> None:
        self.task = task


@pytest.mark.asyncio
@pytest.mark.parametrize("wait", WAITS)
@pytest.mark.parametrize("request_", ["read", "write", "call"])
async def test_a_request_cancelled_with_its_response_is_cancelled(monkeypatch, wait, request_):
    async with opcua_link(VirtualController(thesis_truth())) as link:
        race = CancelWithResponse(link, monkeypatch, wait)

        async def one():
            if request_ == "read":
                return await link._read(("state",))
            if request_ == "write":
                return await link._write("busy", 0.0)
            return await link._call("abort")

        task = asyncio.create_task(one())
        race.arm(task)
        await asyncio.wait({task})
        assert race.fired == 1
        assert task.cancelled(), task.result()


@pytest.mark.asyncio
@pytest.mark.parametrize("wait", WAITS)
async def test_an_abort_landing_with_a_response_stops_the_capture(monkeypatch, wait):
    """The lost abort: the session cancels the capture of a running program; the cancel lands
    with a ring read's response. The capture ends (before: it read on, the abort lost)."""
    truth = thesis_truth()
    ctrl = VirtualController(truth, time_scale=0.05)
    job = make_job(truth, "fanuc")
    ctrl.files.update(job.files)
    async with opcua_link(ctrl) as link:
        race = CancelWithResponse(link, monkeypatch, wait)
        hits: list = []
        first = asyncio.Event()

        async def capture() -> None:
            async for hit in link.run(job):
                hits.append(hit)
                first.set()

        task = asyncio.create_task(capture())
        await asyncio.wait({task, asyncio.ensure_future(first.wait())},
                           return_when=asyncio.FIRST_COMPLETED)
        assert not task.done() or task.exception() is None
        race.arm(task)  # the abort, landing with the next response the capture awaits
        done, _ = await asyncio.wait({task}, timeout=60)  # a safety net: the run is minutes
        got = len(hits)
        if not done:
            task.cancel()  # the lost abort: stop it here to report
            await asyncio.wait({task})
        assert race.fired == 1
        assert done and task.cancelled(), f"capture went on after the abort ({got} hits)"
        assert got < job.touch_count
