"""The last map of the linear axes on the OPC UA results server, read by a client over
Basic256Sha256: ``Map`` beside ``Check`` with the journaled map's figures in µm (each with its
EngineeringUnits), its verdict and evaluation, covered strokes and what is not observable; a
machine without a map shows NaN; a map journaled beside the running server (``rumba map
--store``) appears without a run."""

from __future__ import annotations

import asyncio
import math
from typing import Any

import pytest
from asyncua import Client, ua

from benchmarks.rigs.opcua_results_helpers import (
    CLIENT_URI,
    NODESETS_DIR,
    PASSWORD,
    USER,
    make_pki,
    server_config,
)
from contracts.opcua_space import MAP_VARIABLES, RESULTS_NAMESPACE_URI
from daemon.opcua import map_nodes
from daemon.opcua.server import ResultServer
from daemon.store import map_results
from daemon.store.journal import Store
from tests.map_result_helpers import journaled_map
from tests.test_map_cli import files  # noqa: F401 (files: the fixture)

pytestmark = [pytest.mark.peer]  # the official nodesets come with node-opcua's install


@pytest.fixture(scope="module")
def journaled(files, tmp_path_factory):  # noqa: F811
    if not NODESETS_DIR.is_dir():
        pytest.skip("node-opcua-nodesets not installed (bash .ci/install-peers.sh node-opcua)")
    tmp = tmp_path_factory.mktemp("mapopcua")
    _, mjson, rep, _ = journaled_map(tmp, files[1])
    return tmp, mjson, rep


async def _read(c: Client, idx: int, machine: str, var: str) -> Any:
    return await c.get_node(ua.NodeId(f"{machine}.Map.{var}", idx)).read_value()


async def test_the_last_map_is_served_with_units_and_follows_new_maps(journaled, tmp_path,
                                                                     monkeypatch):
    tmp, mjson, rep = journaled
    monkeypatch.setattr(map_nodes, "POLL_S", 0.1)
    store = Store(tmp / "journal.sqlite")
    (m,) = map_results.listed(store)
    cert, key, _ = await make_pki(tmp_path)
    cfg = server_config(tmp_path, cert.parent)
    srv = ResultServer(cfg, store, ["mill1", "mill2"])
    url = await srv.start()
    try:
        c = Client(url, timeout=10)
        c.application_uri = CLIENT_URI
        await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
        c.set_user(USER)
        c.set_password(PASSWORD)
        async with c:
            idx = (await c.get_namespace_array()).index(RESULTS_NAMESPACE_URI)
            # every variable of the contract, and nothing else
            kids = await c.get_node(ua.NodeId("mill1.Map", idx)).get_children()
            names = {(await k.read_browse_name()).Name for k in kids}
            assert names == {v.name for v in MAP_VARIABLES}
            assert await _read(c, idx, "mill1", "LastMapId") == m.id
            vmax = await _read(c, idx, "mill1", "VolumetricMax_um")
            assert vmax == pytest.approx(m.volumetric_max_um, rel=1e-12)
            assert await _read(c, idx, "mill1", "VolumetricMaxU_um") == pytest.approx(
                m.volumetric_max_u_um, rel=1e-12)
            assert await _read(c, idx, "mill1", "VolumetricRms_um") == pytest.approx(
                m.volumetric_rms_um, rel=1e-12)
            assert await _read(c, idx, "mill1", "PositioningMaxEXX_um") == pytest.approx(
                m.figures["positioning_max_um"]["EXX"]["value_um"], rel=1e-12)
            assert await _read(c, idx, "mill1", "LastMapVerdict") == "WARN"
            assert await _read(c, idx, "mill1", "LastMapEvaluation") == 1  # over a warn limit
            assert await _read(c, idx, "mill1", "Placements") == 2
            assert await _read(c, idx, "mill1", "NotObservable") == list(
                m.figures["unobservable"])
            assert "X " in await _read(c, idx, "mill1", "CoveredRange_mm")
            eu = await c.get_node(ua.NodeId("mill1.Map.VolumetricMax_um.EngineeringUnits",
                                            idx)).read_value()
            assert eu.DisplayName.Text == "µm" and eu.UnitId == 0x3448  # UNECE "4H"
            # a machine without a map: no id, NaN figures (never a stale or zero number)
            assert await _read(c, idx, "mill2", "LastMapId") == ""
            assert math.isnan(await _read(c, idx, "mill2", "VolumetricMax_um"))
            # a map journaled beside the running server appears on its own
            other = Store(tmp / "journal.sqlite")
            other.new_run("JOB-7", "mill2", "hmi", state="DONE")
            new = map_results.record_map_result(other, "JOB-7", mjson, rep)
            other.close()
            for _ in range(600):  # the server polls every 0.1 s here; bounded, not timed
                if await _read(c, idx, "mill2", "LastMapId") == new.id:
                    break
                await asyncio.sleep(0.05)
            assert await _read(c, idx, "mill2", "LastMapId") == "JOB-7"
            assert await _read(c, idx, "mill2", "VolumetricRms_um") == pytest.approx(
                new.volumetric_rms_um, rel=1e-12)
    finally:
        await srv.stop()
        store.close()
