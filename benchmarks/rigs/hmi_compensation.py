"""The daemon with its operator page and the simulated CNC it probes over OPC UA, for the
compensation path: the thesis machine with its Siemens controller_kinematics section, one run
to its end, the compensation view over HTTP (tests/test_hmi_compensate.py,
benchmarks/bench_compensation.py)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import yaml

from benchmarks.rigs.daemon_helpers import CONFIG, write_daemon_yaml
from daemon.config import load_daemon_config
from daemon.service.service import Service

TOKEN = "t0k3n-for-compensation-0123"
THESIS = CONFIG / "machines/thesis_wcbxfzyt.yaml"


@contextlib.asynccontextmanager
async def world(tmp: Path, *, section: bool = True, wide: bool = True,
                plan: str = "thesis_ch3_7poses") -> AsyncIterator[Service]:
    """The daemon (HMI on a free port) and the simulated CNC it probes over OPC UA; the machine
    file is the thesis one with its Siemens section (``wide``: guards widened so that EX0C
    −106 µm passes), or without the section."""
    from simulators.controller import VirtualController
    from simulators.frontends.opcua import OpcUaFrontend
    from simulators.truth import TruthModel

    truth = TruthModel.from_files(THESIS, CONFIG / "artefacts/thesis_4ball.yaml",
                                  CONFIG / "errors/thesis_tableB2.yaml")
    sim = OpcUaFrontend(VirtualController(truth, time_scale=0.03, dialect="siemens"),
                        security="none")
    url = await sim.start()
    try:
        data = yaml.safe_load(THESIS.read_text())
        assert data["controller_kinematics"]["family"] == "siemens"
        if section and wide:
            data["controller_kinematics"]["guards"] = {"max_change_um": 150,
                                                       "max_total_um": 300}
        elif not section:
            del data["controller_kinematics"]
        (tmp / "machine.yaml").write_text(yaml.safe_dump(data))
        path = write_daemon_yaml(tmp, token=TOKEN, plan=plan, dialect="siemens",
                                 link=f"{{transport: opcua, url: '{url}', security: none}}")
        path.write_text(path.read_text().replace(str(THESIS), str(tmp / "machine.yaml")))
        svc = Service(load_daemon_config(path))
        await svc.start()
        try:
            yield svc
        finally:
            await svc.stop()
    finally:
        await sim.stop()


async def run_once(svc: Service) -> str:
    """One verification run on the simulated CNC, to its end: its id."""
    session = svc.sessions["mill1"]
    run_id = session.start("hmi")
    async with asyncio.timeout(120):
        await session.wait()
    assert svc.store.run(run_id).state == "DONE", svc.store.run(run_id)
    return run_id


def bearer() -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKEN}"}


async def get_state(http: aiohttp.ClientSession, svc: Service) -> dict:
    r = await http.get(svc.hmi_url + "api/compensation?machine=mill1", headers=bearer())
    assert r.status == 200, await r.text()
    return await r.json()
