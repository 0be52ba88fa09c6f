"""A run's CAPTURE: one checked program streamed, each hit journaled on arrival (raw data first),
and the ball visits the outlier test names probed again (``run/reprobe.py``)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import replace

from contracts.jobs import RunClock
from contracts.messages import ProbeHit
from daemon.analysis import pipeline
from daemon.analysis.result import Analysis
from daemon.run import reprobe
from daemon.run.ending import RunEnding
from daemon.run.phases import ControllerSilent, RunFailed, State
from daemon.run.temperatures import TemperatureRecorder

log = logging.getLogger("rumba.session")


class RunCapture(RunEnding):
    """The session's capture steps (``daemon.run.session.Session`` is one)."""

    temps: TemperatureRecorder
    clock: RunClock  # the run's one clock, every program's hits and temperatures on it

    async def _reprobe(self, run_id: str, hits: list[ProbeHit],
                       reference: tuple[str, Analysis] | None) -> list[ProbeHit]:
        """Ball visits the outlier test names (a chip, dirt, a bad trigger) are probed again
        after the program, their poses in one more checked program, up to ``reprobe_max``
        rounds (``run/reprobe.py``); every hit is journaled, the analysis uses the clean visit."""
        for rnd in range(1, self.setup.reprobe_max + 1):
            try:
                rp = await asyncio.to_thread(reprobe.plan_reprobe, self.setup, hits, run_id,
                                             rnd, reference[1] if reference else None)
            except pipeline.PipelineError as e:  # the faulty visits stay unrepaired: ERROR
                log.warning("%s %s: no re-probe: %s", self.setup.name, run_id, e)
                break
            if rp is None:
                break
            log.info("%s %s: re-probe %d of %s", self.setup.name, run_id, rnd,
                     "; ".join(rp.faults))
            self.total += rp.prepared.job.touch_count
            self.store.set_state(run_id, str(self.state), touch_total=self.total)
            # its temperatures are the round's, at the plan poses it probes again
            self.temps.begin_reprobe(run_id, rnd, tuple(p for _, p in rp.slots),
                                     self.clock.t_s())
            hits = hits + await self._capture(rp.prepared, rp.remap)
        return hits

    async def _capture(self, prepared: pipeline.Prepared,
                       remap: Callable[[ProbeHit], ProbeHit] | None = None) -> list[ProbeHit]:
        """Stream one program and journal its hits (``remap``: a re-probe's identities), every
        program of the run on the run's clock (``contracts.jobs.RunClock``)."""
        run_id = self.run_id or prepared.job.run_id
        hits: list[ProbeHit] = []
        done0 = self.done
        self._probing(prepared.job.touches.get(1))
        handed = time.monotonic()  # a link that does not start the clock: its program's start
        agen = self.link.run(replace(prepared.job, clock=self.clock))
        # a program started at the machine (NC start by its PLC or the operator): the first
        # result may take as long as the link waits for that start
        first_s = max(self.setup.touch_timeout_s, getattr(self.link, "start_timeout_s", 0.0))
        try:
            while True:
                try:
                    hit = await asyncio.wait_for(
                        anext(agen), first_s if not hits else self.setup.touch_timeout_s)
                except StopAsyncIteration:
                    break
                except TimeoutError:
                    raise ControllerSilent(
                        f"no probe result for {self.setup.touch_timeout_s:g} s after touch "
                        f"{self.done} of {self.total}: controller silent (feed hold, RESET, "
                        "alarm or lost results)") from None
                if not self.clock.started:  # a link stamping nothing (LinuxCNC's lines)
                    self.clock.start(handed)
                own = prepared.complete(hit, self.clock.t_s())  # where it stamped nothing
                hit = own if remap is None else remap(own)
                self.store.journal_hit(run_id, hit)  # raw data first, always
                self._raise_if_stopped()  # journaled, then stopped: nothing lost
                await self.temps.on_hit(run_id, hit.pose, hit.t_s)
                hits.append(hit)
                self.done = done0 + len(hits)
                self._probing(hit if remap is not None else
                              prepared.job.touches.get(own.seq + 1) or own)
                if self.first_hit_at is None:
                    self.first_hit_at = time.time()
                    self._enter(State.CAPTURE)
                else:
                    self._publish()
                mismatch = prepared.mismatch(own)
                if mismatch:
                    raise RunFailed(mismatch)
                if not hit.triggered:
                    raise RunFailed(f"probe did not trigger at touch {hit.seq} (pose {hit.pose}, "
                                    f"ball {hit.ball}, touch {hit.touch}): ball missing or "
                                    "moved; run stopped")
        finally:
            with contextlib.suppress(Exception):
                await agen.aclose()
        if len(hits) != prepared.job.touch_count:
            raise RunFailed(f"program ended after {len(hits)} of {prepared.job.touch_count} "
                            "touches")
        return hits
