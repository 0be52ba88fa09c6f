"""Ctrl-C during the fleet demo is an interruption, whatever the wait then fails with: the
terminal's SIGINT also reaches the daemons, so the demo's poll of a daemon's HMI can fail with
a refused connection before the cancellation lands (that was a traceback)."""

from __future__ import annotations

import asyncio
import os
import signal

import pytest

from demos.fleet import DemoFailed, interruptible


async def _ctrl_c_then(fail_with: BaseException | None) -> int:
    os.kill(os.getpid(), signal.SIGINT)  # handled by the loop: interruptible's handler
    try:
        await asyncio.sleep(30)
    except asyncio.CancelledError:
        if fail_with is not None:  # what the poll raised instead of the cancellation
            raise fail_with from None
        raise
    return 0


@pytest.mark.parametrize("fail_with", [None, ConnectionRefusedError(111, "refused"),
                                       DemoFailed("hmc-fanuc: the daemon exited (code -2)")])
async def test_ctrl_c_ends_the_demo_as_an_interruption(fail_with):
    # asyncio.timeout, not wait_for: a KeyboardInterrupt out of a task of its own would be
    # re-raised by the event loop itself, past pytest.raises
    with pytest.raises(KeyboardInterrupt):
        async with asyncio.timeout(20):
            await interruptible(_ctrl_c_then(fail_with))


async def test_without_ctrl_c_a_failure_is_that_failure():
    async def work() -> int:
        raise DemoFailed("mill-siemens: run X FAILED: probe did not trigger")

    with pytest.raises(DemoFailed, match="probe did not trigger"):
        await interruptible(work())
    assert await interruptible(asyncio.sleep(0, result=7)) == 7
