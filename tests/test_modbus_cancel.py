"""A cancellation that arrives with a Modbus response is not lost (drivers/modbus/registers.py
``keep_cancel``): Python 3.11's ``asyncio.wait_for``, under which pymodbus waits for every
response, swallows it; a start-request poll then carried on and the daemon's stop hung."""

from __future__ import annotations

import asyncio
import sys

import pytest

from daemon.run.ending import cancel_until_done
from drivers.modbus.registers import keep_cancel


async def _response_and_cancel_in_one_step(wrap: bool) -> asyncio.Task:
    """A read waiting as pymodbus waits (``wait_for`` on the response future); the response
    and the task's cancellation land in the same loop step."""
    response = asyncio.get_running_loop().create_future()

    async def read() -> int:
        request = asyncio.wait_for(response, timeout=5.0)
        return await (keep_cancel(request) if wrap else request)

    task = asyncio.create_task(read())
    await asyncio.sleep(0)  # the read waits for its response
    response.set_result(7)
    task.cancel()
    await asyncio.wait({task})
    return task


@pytest.mark.asyncio
async def test_a_cancel_arriving_with_the_response_cancels_the_read():
    task = await _response_and_cancel_in_one_step(wrap=True)
    assert task.cancelled()


@pytest.mark.asyncio
@pytest.mark.skipif(sys.version_info >= (3, 12), reason="CPython gh-86296 is fixed in 3.12")
async def test_without_it_python_3_11_loses_the_cancel():
    """The defect itself, on the Python this project runs: the read returns its value."""
    task = await _response_and_cancel_in_one_step(wrap=False)
    assert not task.cancelled() and task.result() == 7


@pytest.mark.asyncio
async def test_a_cleanup_running_after_its_own_cancel_is_not_cut_again():
    """A task already cancelled (its abort's cleanup writing to the controller) keeps its
    reads: ``keep_cancel`` raises only a cancellation requested during the call."""
    done = []

    async def run() -> None:
        try:
            await asyncio.sleep(10)
        except asyncio.CancelledError:
            done.append(await keep_cancel(asyncio.sleep(0, result="abort written")))
            raise

    task = asyncio.create_task(run())
    await asyncio.sleep(0)
    task.cancel()
    await asyncio.wait({task})
    assert task.cancelled() and done == ["abort written"]


@pytest.mark.asyncio
async def test_the_stop_cancels_again_a_poll_that_swallowed_its_cancel():
    """A poll loop that lost one cancellation (as above) is cancelled again until it ends:
    the daemon's stop returns."""
    swallowed = []

    async def poll() -> None:
        while True:
            try:
                await asyncio.sleep(0.01)
            except asyncio.CancelledError:
                if not swallowed:  # the first one lost, as wait_for loses it
                    swallowed.append(True)
                    continue
                raise

    task = asyncio.create_task(poll())
    await asyncio.sleep(0.02)
    async with asyncio.timeout(30):  # a hang fails here with the reason, not the suite
        await cancel_until_done(task)
    assert swallowed and task.cancelled()
