"""A run's temperature channels: read at the start, at every pose and at the
end, each reading journaled on arrival; a channel that cannot be read is journaled with the
reason and logged as a warning, never stops the run nor holds it up."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
from typing import Any

from contracts.temperatures import TemperatureChannel, TemperatureReading, summarise
from daemon.store.journal import Store
from daemon.store.temperatures import journal_temperature, temperatures
from drivers.base import ChannelMissing, CncLink
from drivers.modbus.transmitter import Transmitter

log = logging.getLogger("rumba.temperatures")

READ_TIMEOUT_S = 3.0  # one sample of every channel; a silent sensor must not hold the run
# a read that failed after waiting this long waited for an answer that did not come (a host
# switched off but routable: no RST, the connect or the request times out); one refused at once
# (an unknown node, a closed port) costs nothing and is tried again at the next pose
NO_ANSWER_S = 0.5
# a run that stops (abort, failure, the daemon stopping) cancels its reads still in flight and
# waits this long for each to unwind (a cancelled socket read ends at once) before it reports
# itself stopped: no read of the run outlives it
STOP_WAIT_S = 2.0
STOPPED = "not read: the run stopped before the channel answered"
# a channel the DNC program prints whose line never came: a print that failed on the control (a
# Sinumerik WRITE refused once its file outgrows MD11420 $MN_LEN_PROTOCOL_FILE, Siemens' job
# planning manual, WRITE) or a line the DNC reader dropped (garbled, a sensor fault code)
NOT_PRINTED = ("not read: no RTEMP line for {where} came from the program (a print that failed on "
               "the control, or a line garbled or out of range on the link)")


@dataclasses.dataclass
class _Read:
    """One read of one channel, journaled exactly once: by the read itself (its value, why not,
    or ``STOPPED`` when the stop cut it) or by ``stop`` (a read cut before it ever ran, or one
    still running after the stop's wait)."""

    run_id: str
    channel: str
    at: str
    pose: int | None
    t_s: float
    rnd: int
    journaled: bool = False


class TemperatureRecorder:
    """The channels of one machine, read through its link or their transmitters.

    The start sample is awaited (bounded by ``READ_TIMEOUT_S``) before the program; the pose
    samples run beside the capture, never awaited by it (a transmitter switched off but still
    routable held every pose up by the timeout); a channel that did not answer in time is
    unreachable for the rest of the run — its pose readings are journaled as not read with
    that reason, without waiting — and is tried again at the end, after the last touch."""

    def __init__(self, machine: str, channels: tuple[TemperatureChannel, ...], link: CncLink,
                 store: Store, link_name: str) -> None:
        self.machine, self.channels, self.link, self.store = machine, channels, link, store
        self.link_name = link_name
        self._transmitters: dict[str, Transmitter] = {}
        self._last_pose: int | None = None
        # the program running: 0 the plan's, k re-probe round k's, whose printed pose k is the
        # plan pose _program_poses[k] (its hits are remapped so: daemon/run/reprobe.py)
        self._round = 0
        self._program_poses: tuple[int, ...] | None = None
        self._rounds: list[int] = [0]  # the programs run (printed channels' accounting)
        self._poses: list[tuple[int, int]] = []  # (round, plan pose) probed, in order
        self._down: dict[str, str] = {}  # channel → why it is unreachable for this run
        self._missing: dict[str, str] = {}  # channel → its address is not on the controller
        # every read started and not yet journaled (start, pose and end reads): the one owner,
        # which ``end`` waits on and ``stop`` accounts from — a read leaves it once journaled
        self._reads: dict[asyncio.Task[None], _Read] = {}

    def sources(self) -> dict[str, str]:
        """Where each channel comes from (the run record's audit field)."""
        return {ch.name: ch.describe(self.link_name) for ch in self.channels}

    def _transmitter(self, ch: TemperatureChannel) -> Transmitter:
        assert ch.transmitter is not None
        key = ch.transmitter.model_dump_json()
        if key not in self._transmitters:
            self._transmitters[key] = Transmitter(ch.transmitter)
        return self._transmitters[key]

    async def _read(self, ch: TemperatureChannel) -> float:
        if ch.transmitter is not None:
            return await self._transmitter(ch).read(ch)
        return await self.link.read_temperature(ch)

    def _polled(self) -> list[TemperatureChannel]:
        return [ch for ch in self.channels
                if ch.transmitter is not None or self.link_name != "serial"]

    def _spawn(self, run_id: str, ch: TemperatureChannel, at: str, pose: int | None,
               t_s: float, rnd: int = 0) -> asyncio.Task[None]:
        """Start one read of ``ch`` (``rnd`` the re-probe round of a pose read, 0 for the run's
        own start and end), owned by ``_reads`` until journaled."""
        rec = _Read(run_id, ch.name, at, pose, t_s, rnd)
        task = asyncio.get_running_loop().create_task(
            self._read_one(ch, rec), name=f"temperature-{self.machine}-{ch.name}")
        self._reads[task] = rec
        task.add_done_callback(self._settled)
        return task

    def _settled(self, task: asyncio.Task[None]) -> None:
        """A read ended: journaled, it is accounted for; else (cut before it ever ran, or its
        journal failed) it stays for ``stop`` to account and ``end`` to raise."""
        rec = self._reads.get(task)
        if rec is not None and rec.journaled:
            del self._reads[task]

    def _put(self, rec: _Read, value: float | None, error: str) -> None:
        """Journal ``rec``'s one row (a second attempt, a late read after ``stop`` journaled it
        as cut, writes nothing)."""
        if rec.journaled:
            log.warning("%s %s: temperature %s (%s) answered after the run stopped: %s "
                        "not journaled", self.machine, rec.run_id, rec.channel, rec.at,
                        "value" if value is not None else error)
            return
        self._journal(rec.run_id, TemperatureReading(
            rec.channel, rec.at, rec.pose, rec.t_s, value, error,  # type: ignore[arg-type]
            rec.rnd))
        rec.journaled = True

    async def _read_one(self, ch: TemperatureChannel, rec: _Read) -> None:
        """Read one channel and journal its value or why not."""
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        try:
            value = await self._answer(ch, rec)
        except asyncio.CancelledError:
            raise
        except ChannelMissing as e:
            # a misspelt address: said once, not read again in this run (not at each pose)
            self._missing[ch.name] = why = str(e)
            log.warning("%s %s: temperature %s: %s; not read again in this run (check the "
                        "channel's address in daemon.yaml)", self.machine, rec.run_id,
                        ch.name, why)
            self._put(rec, None, why)
        except Exception as e:
            why = (f"no answer in {READ_TIMEOUT_S:g} s" if isinstance(e, TimeoutError)
                   else str(e) or type(e).__name__)
            if loop.time() - t0 >= NO_ANSWER_S and rec.at != "end":
                where = f"pose {rec.pose}" if rec.at == "pose" else rec.at
                self._down[ch.name] = f"{why} at {where}"
                why += "; not read again until the end of the run"
            log.warning("%s %s: temperature %s not read (%s): %s", self.machine, rec.run_id,
                        ch.name, rec.at, why)
            self._put(rec, None, why)
        else:
            self._put(rec, float(value), "")

    async def _answer(self, ch: TemperatureChannel, rec: _Read) -> float:
        """The channel's value within ``READ_TIMEOUT_S`` (TimeoutError else). Cancelled (the run
        stopped): a value that had already come is journaled — nothing received is lost,
        whatever a Python version's ``asyncio.wait_for`` does with a cancel that meets a done
        read (gh-86296) — else the read is cut and journaled as ``STOPPED``; the cancel goes
        on."""
        read = asyncio.ensure_future(self._read(ch))
        try:
            done, _ = await asyncio.wait((read,), timeout=READ_TIMEOUT_S)
        except asyncio.CancelledError:
            if not read.done():
                read.cancel()  # the transmitter drops its connection: no late answer
                await asyncio.wait((read,), timeout=STOP_WAIT_S)
            got = (None if not read.done() or read.cancelled() or read.exception() is not None
                   else float(read.result()))
            try:
                self._put(rec, got, "" if got is not None else STOPPED)
            except Exception as e:  # the journal gone must not hide the stop
                log.error("%s %s: temperature %s not journaled: %s", self.machine, rec.run_id,
                          ch.name, e)
            raise
        if not done:
            read.cancel()  # unwound (its connection dropped) before the next, bounded
            await asyncio.wait((read,), timeout=STOP_WAIT_S)
            raise TimeoutError
        return float(read.result())

    async def sample(self, run_id: str, at: str, pose: int | None, t_s: float) -> None:
        """Read every polled channel now (an unreachable one too: the start and the end try
        every channel, but one whose address is not on the controller) and journal each value
        or why it failed."""
        for ch in self._polled():
            if ch.name in self._missing:
                self._journal(run_id, TemperatureReading(ch.name, at, pose, t_s, None,
                                                         f"not read: {self._missing[ch.name]}"))
        await self._settle([self._spawn(run_id, ch, at, pose, t_s) for ch in self._polled()
                            if ch.name not in self._missing])

    @staticmethod
    async def _settle(tasks: list[asyncio.Task[None]]) -> None:
        """Wait for ``tasks`` (each bounded by its timeout); a journal that failed fails the
        run. Cancelled meanwhile (the run stopped): the reads are left running, still owned by
        ``_reads``, for ``stop`` to cut and account — waiting never cancels them itself."""
        if not tasks:
            return
        await asyncio.wait(tasks)
        for task in tasks:
            if not task.cancelled() and task.exception() is not None:
                raise task.exception()  # type: ignore[misc]

    def _busy(self, channel: str) -> bool:
        return any(rec.channel == channel and not task.done()
                   for task, rec in self._reads.items())

    def _sample_pose(self, run_id: str, pose: int, t_s: float) -> None:
        """Start the pose's reads beside the capture; what cannot be read now is journaled
        now with the reason (unreachable since …, or the last read still in flight)."""
        rnd = self._round
        for ch in self._polled():
            if ch.name in self._missing:
                why = f"not read: {self._missing[ch.name]}"
            elif ch.name in self._down:
                why = (f"not read: unreachable since {self._down[ch.name]}; tried again at "
                       "the end of the run")
            elif self._busy(ch.name):
                why = "not read: the previous read of this channel is still waiting"
            else:
                self._spawn(run_id, ch, "pose", pose, t_s, rnd)
                continue
            self._journal(run_id, TemperatureReading(ch.name, "pose", pose, t_s, None, why,
                                                     rnd))

    async def on_hit(self, run_id: str, pose: int, t_s: float) -> None:
        """After a journaled hit: the program's printed values, and a sample at a new pose
        (started, not awaited)."""
        self.take_printed(run_id, t_s)
        if pose != self._last_pose:
            self._last_pose = pose
            if (self._round, pose) not in self._poses:
                self._poses.append((self._round, pose))
            self._sample_pose(run_id, pose, t_s)

    def begin_reprobe(self, run_id: str, round_: int, poses: tuple[int, ...], t_s: float
                      ) -> None:
        """Before re-probe round ``round_``'s program (``daemon/run/reprobe.py``), whose pose k
        is the plan's pose ``poses[k]``: what the last program printed is journaled as its own,
        then this program's readings are journaled as the round's — a printed pose under the
        plan pose it re-probes, its start and end lines as the round's, never as the run's
        (``contracts.temperatures.run_ends``) — and its first pose is sampled even when the
        last program ended on it."""
        self.take_printed(run_id, t_s)
        self._round, self._program_poses = round_, tuple(poses)
        self._rounds.append(round_)
        self._last_pose = None

    def _printed(self) -> list[TemperatureChannel]:
        return [ch for ch in self.channels
                if ch.transmitter is None and self.link_name == "serial"]

    def account_printed(self, run_id: str, t_s: float) -> None:
        """After the last touch: a printed channel's start, pose or end line that never came is
        journaled as not read with the reason (``NOT_PRINTED``), as a polled channel's failed
        read is — nothing the program should have said goes missing unsaid."""
        printed = self._printed()
        if not printed:
            return
        have = {(r.channel, r.at, r.pose, r.reprobe_round)
                for r in temperatures(self.store, run_id)}
        due = [d for k in self._rounds for d in (
            ("start", None, k), *(("pose", p, k) for kk, p in self._poses if kk == k),
            ("end", None, k))]
        for ch in printed:
            for at, pose, k in due:
                if (ch.name, at, pose, k) not in have:
                    where = f"pose {pose}" if at == "pose" else f"the {at}"
                    where += f" of re-probe {k}" if k else ""
                    log.warning("%s %s: temperature %s: no RTEMP line for %s", self.machine,
                                run_id, ch.name, where)
                    self._journal(run_id, TemperatureReading(
                        ch.name, at, pose, t_s, None,  # type: ignore[arg-type]
                        NOT_PRINTED.format(where=where), k))

    def take_printed(self, run_id: str, t_s: float) -> None:
        """Journal what the program printed since the last call (a DNC program's ``RTEMP``
        lines: channel k is the k-th controller channel, the program prints them in order; a
        pose by the program's own index, the plan's pose in a re-probe's: ``begin_reprobe``)."""
        printed = self._printed()
        if not printed:
            return
        for k, marker, value in self.link.printed_temperatures():
            if not 1 <= k <= len(printed):
                log.warning("%s %s: temperature line of channel %d ignored (the program "
                            "prints %d)", self.machine, run_id, k, len(printed))
                continue
            at = {"S": "start", "E": "end"}.get(marker, "pose")
            pose = int(marker[1:]) if at == "pose" else None
            if pose is not None and self._program_poses is not None:
                if pose >= len(self._program_poses):
                    log.warning("%s %s: temperature line of pose %d ignored (re-probe %d "
                                "probes %d poses)", self.machine, run_id, pose, self._round,
                                len(self._program_poses))
                    continue
                pose = self._program_poses[pose]
            self._journal(run_id, TemperatureReading(
                printed[k - 1].name, at, pose, t_s, value,  # type: ignore[arg-type]
                "", self._round))

    def _journal(self, run_id: str, r: TemperatureReading) -> None:
        journal_temperature(self.store, run_id, r)

    def summary(self, run_id: str) -> dict[str, Any] | None:
        """The run's summary (contracts.temperatures.summarise), None without channels."""
        if not self.channels:
            return None
        return summarise(temperatures(self.store, run_id), self.sources())

    async def start(self, run_id: str, t_s: float) -> None:
        """Before the program: the first sample."""
        self.abandon()
        self._last_pose = None
        self._round, self._program_poses, self._rounds = 0, None, [0]
        self._poses = []
        self._down.clear()
        self._missing.clear()
        await self.sample(run_id, "start", None, t_s)

    async def end(self, run_id: str, t_s: float) -> None:
        """After the last touch (re-probes included): what was printed, the pose reads still
        in flight (each bounded by the timeout), the last sample of every channel."""
        self.take_printed(run_id, t_s)
        self.account_printed(run_id, t_s)
        # the pose reads still in flight stay in ``_reads`` while waited for: a stop that comes
        # now cuts and accounts for them as for any other (they were once taken out of its
        # sight here, and one cut before it ever ran was journaled by nobody)
        await self._settle(list(self._reads))
        await self.sample(run_id, "end", None, t_s)
        await self.close()

    def abandon(self) -> None:
        """Cancel the reads in flight (``stop`` also waits for them and accounts for each)."""
        for task in self._reads:
            task.cancel()

    async def stop(self, run_id: str) -> None:
        """A run ended without its end sample (aborted, failed, the daemon stopping), wherever
        it was — capturing, or waiting in ``end`` for its last reads: each read not yet
        journaled is cancelled and awaited — it journals the value it had received, or
        ``STOPPED`` — one cut before it ever ran is journaled ``STOPPED`` here, and the
        transmitters are closed, before the run reports itself stopped: nothing of the run
        outlives it, nothing it received is lost, each read has exactly one row."""
        reads = dict(self._reads)
        live = [t for t in reads if not t.done()]
        self.abandon()
        if live:
            _, left = await asyncio.wait(live, timeout=2 * STOP_WAIT_S)
            for task in left:  # a read that ignores its cancellation: said, never hidden
                log.error("%s %s: temperature read %s still running after the run stopped",
                          self.machine, run_id, task.get_name())
        for task, rec in reads.items():
            if task.done() and not task.cancelled() and task.exception() is not None:
                log.error("%s %s: temperature %s (%s) not journaled: %s", self.machine,
                          rec.run_id, rec.channel, rec.at, task.exception())
            if not rec.journaled:  # cut before it ran, or still running: cut all the same
                try:
                    self._put(rec, None, STOPPED)
                except Exception as e:  # the journal gone must not hide the stop
                    log.error("%s %s: temperature %s not journaled: %s", self.machine,
                              rec.run_id, rec.channel, e)
            self._reads.pop(task, None)
        await self.close()

    def with_summary(self, run_id: str, analysis: Any) -> Any:
        """``analysis`` (a ``pipeline.RunAnalysis``) with the run's summary in its data."""
        temps = self.summary(run_id)
        if temps is None:
            return analysis
        return dataclasses.replace(analysis, data=dataclasses.replace(analysis.data,
                                                                      temperatures=temps))

    async def close(self) -> None:
        """Drop the transmitters' connections (the next run opens them again)."""
        self.abandon()
        transmitters, self._transmitters = list(self._transmitters.values()), {}
        for t in transmitters:
            with contextlib.suppress(Exception):
                await t.close()
