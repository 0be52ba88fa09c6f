"""How a run ends short of its verdict, and the verdict's way to the CNC: the controller stopped
through the link's ``abort()``, the end state journaled with its phase and cause, ERROR written
back — each step bounded, in a task a second cancellation cannot cut short."""

from __future__ import annotations

import asyncio
import logging

from contracts.jobs import Verdict
from daemon.run.phases import RunStatus, State
from daemon.run.temperatures import TemperatureRecorder
from drivers.base import CncLink, LinkError

log = logging.getLogger("rumba.session")

ABORT_TIMEOUT_S = 10.0
WRITE_BACK_TIMEOUT_S = 30.0


class RunEnding(RunStatus):
    """The session's stopping and write-back steps (``daemon.run.session.Session`` is one)."""

    link: CncLink
    temps: TemperatureRecorder  # the run's temperature channels
    _abort_reason: str | None
    _controller_dirty: bool

    def _raise_if_stopped(self) -> None:
        """Stop here if a stop was asked whose cancellation a library swallowed: Python 3.11's
        ``asyncio.wait_for`` returns a result that completed together with the cancel
        (gh-86296), and the run went on to DONE after a SIGTERM on ``rumba verify``."""
        task = asyncio.current_task()
        if self._abort_reason is not None or (task is not None and task.cancelling()):
            raise asyncio.CancelledError

    async def _end(self, run_id: str, state: State, reason: str, *, stop: bool) -> None:
        """Stop the controller, journal the end state with its reason, tell the CNC: in a task
        of its own that a second cancellation (asyncio.run tearing the loop down after Ctrl-C)
        cannot cut short; every step is bounded by its timeout. Re-raises that cancellation
        once the end is recorded."""
        async def finish() -> None:
            # the run's temperature reads in flight are cancelled beside the controller's stop
            # (never delaying it) and awaited before the end is journaled: nothing of the run
            # outlives it (a pose read kept the link busy and journaled ~3 s after ABORTED)
            reads = asyncio.ensure_future(self.temps.stop(run_id))
            why = await self._stop_controller() if stop else None
            try:
                await reads
            except Exception as e:
                log.error("%s %s: temperature reads not stopped: %s", self.setup.name, run_id, e)
            try:
                self._enter(state, f"{reason}; controller abort failed: {why}" if why
                            else reason)
            except Exception as e:  # the journal gone must not hide the end of the run
                log.error("%s %s: could not journal %s: %s", self.setup.name, run_id, state, e)
            await self._write_back(Verdict("ERROR", run_id, reason), strict=False)

        cleanup = asyncio.get_running_loop().create_task(finish(), name=f"end-{run_id}")
        cancelled = False
        while not cleanup.done():
            try:
                await asyncio.shield(cleanup)
            except asyncio.CancelledError:
                cancelled = True
        cleanup.result()
        if cancelled:
            raise asyncio.CancelledError

    async def _clear_leftover(self) -> None:
        """Stop a program the last run left on the controller before loading a new one."""
        try:
            await asyncio.wait_for(self.link.abort(), ABORT_TIMEOUT_S)
        except Exception as e:
            raise LinkError(f"the program of the last run could not be stopped on the "
                            f"controller: {str(e) or type(e).__name__}") from None
        self._controller_dirty = False

    async def _stop_controller(self) -> str | None:
        """Feed hold / reset / unload as the link's ``abort()`` does it; None when done, else
        why not (kept: the next run stops the leftover program first)."""
        try:
            await asyncio.wait_for(self.link.abort(), ABORT_TIMEOUT_S)
        except Exception as e:
            self._controller_dirty = True
            log.warning("%s: abort on the controller failed: %s", self.setup.name,
                        str(e) or type(e).__name__)
            return str(e) or type(e).__name__
        self._controller_dirty = False
        return None

    async def _write_back(self, verdict: Verdict, strict: bool) -> None:
        """Write the verdict where the CNC reads it; when ``strict`` a failure fails the run."""
        if not self.link.capabilities.writes_verdict:
            return
        try:
            await asyncio.wait_for(self.link.write_verdict(verdict), WRITE_BACK_TIMEOUT_S)
        except Exception as e:
            if strict:
                raise LinkError(f"verdict {verdict.status} computed but not written back "
                                f"to the controller: {e}") from None
            log.warning("%s: could not write %s to the controller: %s", self.setup.name,
                        verdict.status, e)


async def await_run(task: asyncio.Task) -> None:
    """Wait for a run task to end, its own cancellation (an abort) included, but never swallow
    the caller's: a service stopping while it waits on a stalled run must stop."""
    try:
        await asyncio.shield(task)
    except asyncio.CancelledError:
        current = asyncio.current_task()
        if current is not None and current.cancelling():
            raise


RECANCEL_S = 0.05  # how soon a task that swallowed its cancellation is cancelled again


async def cancel_until_done(task: asyncio.Task) -> None:
    """Cancel ``task`` and wait until it has ended, cancelling it again while it runs on.

    Python 3.11's ``asyncio.wait_for`` returns the inner result instead of raising when the
    result arrives in the same loop step as the cancellation (CPython gh-86296, fixed in 3.12);
    pymodbus waits for every response under it, and a start-request poll cancelled at that
    instant carried on (a Modbus daemon's stop hung for good in one CI run, its run done, the
    poll still reading; every Modbus call now re-raises such a cancellation itself,
    ``drivers.modbus.registers.keep_cancel``). For pollers only: a task whose cancellation
    runs cleanup (a run's abort) must not be cancelled again. The waiting caller's own
    cancellation is never swallowed."""
    while not task.done():
        task.cancel()
        await asyncio.wait({task}, timeout=RECANCEL_S)
