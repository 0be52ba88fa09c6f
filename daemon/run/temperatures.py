"""A run's temperature channels (issue 22 item 3): read at the start, at every pose and at the
end, each reading journaled on arrival; a channel that cannot be read is journaled with the
reason and logged as a warning, never stops the run."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from typing import Any

from contracts.temperatures import TemperatureChannel, TemperatureReading, summarise
from daemon.store.journal import Store
from daemon.store.temperatures import journal_temperature, temperatures
from drivers.base import CncLink
from drivers.modbus.transmitter import Transmitter

log = logging.getLogger("rumba.temperatures")

READ_TIMEOUT_S = 3.0  # one sample of every channel; a silent sensor must not hold the run


class TemperatureRecorder:
    """The channels of one machine, read through its link or their transmitters."""

    def __init__(self, machine: str, channels: tuple[TemperatureChannel, ...], link: CncLink,
                 store: Store, link_name: str) -> None:
        self.machine, self.channels, self.link, self.store = machine, channels, link, store
        self.link_name = link_name
        self._transmitters: dict[str, Transmitter] = {}
        self._last_pose: int | None = None

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

    async def sample(self, run_id: str, at: str, pose: int | None, t_s: float) -> None:
        """Read every polled channel now and journal each value or why it failed."""
        polled = [ch for ch in self.channels
                  if ch.transmitter is not None or self.link_name != "serial"]
        if not polled:
            return
        got = await asyncio.gather(*(asyncio.wait_for(self._read(ch), READ_TIMEOUT_S)
                                     for ch in polled), return_exceptions=True)
        for ch, value in zip(polled, got, strict=True):
            if isinstance(value, asyncio.CancelledError):
                raise value
            if isinstance(value, BaseException):
                why = (f"no answer in {READ_TIMEOUT_S:g} s" if isinstance(value, TimeoutError)
                       else str(value) or type(value).__name__)
                log.warning("%s %s: temperature %s not read (%s): %s", self.machine, run_id,
                            ch.name, at, why)
                self._journal(run_id, TemperatureReading(ch.name, at, pose, t_s, None, why))
            else:
                self._journal(run_id, TemperatureReading(ch.name, at, pose, t_s, float(value)))

    async def on_hit(self, run_id: str, pose: int, t_s: float) -> None:
        """After a journaled hit: the program's printed values, and a sample at a new pose."""
        self.take_printed(run_id, t_s)
        if pose != self._last_pose:
            self._last_pose = pose
            await self.sample(run_id, "pose", pose, t_s)

    def take_printed(self, run_id: str, t_s: float) -> None:
        """Journal what the program printed since the last call (a DNC program's ``RTEMP``
        lines: channel k is the k-th controller channel, the program prints them in order)."""
        printed = [ch for ch in self.channels
                   if ch.transmitter is None and self.link_name == "serial"]
        for k, marker, value in self.link.printed_temperatures():
            if not 1 <= k <= len(printed):
                log.warning("%s %s: temperature line of channel %d ignored (the program "
                            "prints %d)", self.machine, run_id, k, len(printed))
                continue
            at = {"S": "start", "E": "end"}.get(marker, "pose")
            self._journal(run_id, TemperatureReading(
                printed[k - 1].name, at, int(marker[1:]) if at == "pose" else None, t_s,
                value))  # type: ignore[arg-type]

    def _journal(self, run_id: str, r: TemperatureReading) -> None:
        journal_temperature(self.store, run_id, r)

    def summary(self, run_id: str) -> dict[str, Any] | None:
        """The run's summary (contracts.temperatures.summarise), None without channels."""
        if not self.channels:
            return None
        return summarise(temperatures(self.store, run_id), self.sources())

    async def start(self, run_id: str, t_s: float) -> None:
        """Before the program: the first sample."""
        self._last_pose = None
        await self.sample(run_id, "start", None, t_s)

    async def end(self, run_id: str, t_s: float) -> None:
        """After the last touch (re-probes included): what was printed, the last sample."""
        self.take_printed(run_id, t_s)
        await self.sample(run_id, "end", None, t_s)

    def with_summary(self, run_id: str, analysis: Any) -> Any:
        """``analysis`` (a ``pipeline.RunAnalysis``) with the run's summary in its data."""
        temps = self.summary(run_id)
        if temps is None:
            return analysis
        return dataclasses.replace(analysis, data=dataclasses.replace(analysis.data,
                                                                      temperatures=temps))

    async def close(self) -> None:
        for t in self._transmitters.values():
            await t.close()
