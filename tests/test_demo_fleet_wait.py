"""The fleet demo waits on each daemon's own run state, not a fixed clock:
a slow run is waited for, a run that fails ends the wait at once with its reason (no
``TimeoutError`` traceback), a daemon that exits is named."""

from __future__ import annotations

import asyncio
import sys

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from daemon.analysis.replay_link import Faults, ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.service.service import Service
from demos.fleet import DemoFailed, runs_ended

TOKEN = "t0k3n-for-fleet-wait-012345"


async def service(tmp_path, faults: Faults, delay_s: float) -> tuple[Service, list]:
    rows = thesis_rows(thesis_setup())
    links: list[ReplayLink] = []

    def link(setup):
        links.append(ReplayLink(rows, setup.machine, delay_s=delay_s, faults=faults))
        return links[-1]

    svc = Service(load_daemon_config(write_daemon_yaml(tmp_path, token=TOKEN)), link,
                  prepare=prepare_from_rows(rows))
    await svc.start()
    return svc, links


async def test_a_slow_run_is_waited_for_to_its_verdict(tmp_path):
    svc, links = await service(tmp_path, Faults(), delay_s=0.03)
    try:
        links[0].request.set()  # the CNC's start-of-shift request
        st = await runs_ended({"mill1": svc.hmi_url}, TOKEN)
        assert st["mill1"]["state"] == "IDLE" and st["mill1"]["verdict"]["status"] == "PASS"
        assert st["mill1"]["done"] == st["mill1"]["total"] > 100
    finally:
        await svc.stop()


async def test_a_failed_run_ends_the_wait_at_once_with_its_reason(tmp_path):
    svc, links = await service(tmp_path, Faults(no_trigger_at=12), delay_s=0.0)
    try:
        links[0].request.set()
        with pytest.raises(DemoFailed, match=r"mill1: run \S+ FAILED: .*probe did not trigger"):
            await runs_ended({"mill1": svc.hmi_url}, TOKEN)
    finally:
        await svc.stop()


async def test_a_daemon_that_exits_is_named(tmp_path):
    svc, _ = await service(tmp_path, Faults(), delay_s=0.0)
    proc = await asyncio.create_subprocess_exec(sys.executable, "-c", "raise SystemExit(3)")
    await proc.wait()
    try:
        with pytest.raises(DemoFailed, match=r"mill1: the daemon exited \(code 3\)"):
            await runs_ended({"mill1": svc.hmi_url}, TOKEN, {"mill1": proc})
    finally:
        await svc.stop()
