"""One run started from the simulated CNC with temperature channels: the daemon's Service up, the
start request raised on the control, the verdict awaited there, the run's journal rows read back
(tests/test_temperature_channels.py, _dnc_dialects.py, _silent.py)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from contracts.temperatures import TemperatureReading
from daemon.config import DaemonConfig
from daemon.service.service import Service
from daemon.store.temperatures import temperatures
from simulators.controller import VirtualController
from tests.test_e2e_transports import RUN_TIMEOUT_S, wait_verdict_on_cnc


@dataclass
class CncRun:
    """What one run left: its session (state, reason) and its journal rows."""

    session: Any
    run_id: str
    readings: list[TemperatureReading]
    analysis: Any
    verdict: dict[str, Any] | None
    report: tuple[Path, Path] | None


async def run_from_cnc(cfg: DaemonConfig, ctrl: VirtualController,
                       machine: str = "mill1") -> CncRun:
    """Start the Service on ``cfg``, raise the start request on ``ctrl``, wait for the verdict on
    the CNC (a failed run raises at once with its reason), read the run's rows, stop."""
    service = Service(cfg)
    await service.start()
    try:
        session = service.sessions[machine]
        ctrl.raise_start_request()
        await wait_verdict_on_cnc(session, ctrl, RUN_TIMEOUT_S)
        run_id = session.run_id
        store = service.store
        return CncRun(session, run_id, temperatures(store, run_id), store.analysis(run_id),
                      store.verdict(run_id), store.report(run_id))
    finally:
        await service.stop()
