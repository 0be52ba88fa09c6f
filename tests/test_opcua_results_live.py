"""The OPC UA results server on a live daemon: ``daemon.yaml`` with ``opcua_server`` and
``aqdef_dir`` → ``Service`` against the simulated CNC over serial (pty), OPC UA and Modbus. The
CNC raises its start-of-shift request once node-opcua (tests/peers/opcua_results_client.js) is
subscribed; node-opcua sees the check running (state, touches), receives the ResultReadyEvent
of the run with the verdict's ResultEvaluation, reads every run's result, downloads the run's
PDF report; the run's AQDEF file lies in the drop folder. And PASS → OK, FAIL → NotOK and a
constructed NotDecidable on live runs."""

from __future__ import annotations

import asyncio
import hashlib
from pathlib import Path

import pytest
import yaml

from benchmarks.rigs.e2e_run import NOISE_SEED, write_config
from benchmarks.rigs.opcua_results_helpers import NODESETS_DIR, PASSWORD, USER, make_pki
from benchmarks.rigs.rig_helpers import make_truth, start_rig
from daemon.config import load_daemon_config
from daemon.service.service import Service
from simulators.controller import VirtualController
from tests.aqdef_reader import read_aqdef
from tests.test_opcua_results import need_node, run_node

EVALUATION = {"PASS": 1, "FAIL": 2}


async def live_config(tmp: Path, link: dict) -> Path:
    cert, _, _ = await make_pki(tmp)
    pw = tmp / "quality.password"
    pw.write_text(PASSWORD)
    pw.chmod(0o600)
    path = write_config(tmp, "fanuc", link)
    doc = yaml.safe_load(path.read_text())
    doc["opcua_server"] = {
        "port": 0, "cert_dir": str(tmp / "server-pki"), "trusted_dir": str(cert.parent),
        "users": {USER: str(pw)}, "nodesets_dir": str(NODESETS_DIR),
        "machines": {"mill1": {"manufacturer": "Acme", "model": "FiveAx 650",
                               "serial_number": "SN-1"}}}
    doc["aqdef_dir"] = str(tmp / "spc")
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    return path


@pytest.mark.peer
@pytest.mark.slow
@pytest.mark.parametrize("transport", ["serial-pty", "opcua", "modbus"])
async def test_node_opcua_follows_a_live_run(tmp_path, transport):
    need_node()
    ctrl = VirtualController(make_truth())
    ctrl.dialect = "fanuc"
    ctrl.reseed(NOISE_SEED)
    rig = await start_rig(transport, ctrl)
    service = None
    try:
        cfg = load_daemon_config(await live_config(tmp_path, rig.link))
        service = Service(cfg)
        await service.start()
        assert service.opcua_url is not None and service.opcua_url.startswith("opc.tcp://127.")
        pki = {"key": tmp_path / "client" / "key.pem", "pem": tmp_path / "client" / "cert.pem"}

        async def start_the_run() -> None:
            ctrl.raise_start_request()  # the CNC's start-of-shift request

        code, lines, err = await run_node(service.opcua_url, pki, "--wait-event", "--timeout",
                                          "240000", on_subscribed=start_the_run, timeout_s=300)
        assert code == 0 and lines[-1]["ok"], (lines[-1:], err[-3000:])
        session = service.sessions["mill1"]
        await session.wait()
        run = service.store.run(session.run_id)
        r = lines[-1]
        assert run.state == "DONE" and run.verdict in EVALUATION, (run.state, run.reason)
        # during the run: the state and the touch count moved, the item state was Executing
        seen = r["seen"]
        assert ["RunId", run.id] in seen and ["MachineryItemState", "Executing"] in seen
        assert any(k == "State" and v == "CAPTURE" for k, v in seen)
        assert any(k == "DoneTouches" and 0 < v < 140 for k, v in seen)
        # after the run: the event, the last verdict, the result by id
        assert r["event"]["result"]["resultId"] == run.id
        assert r["event"]["result"]["evaluation"] == EVALUATION[run.verdict]
        assert (r["after"]["LastResultId"], r["after"]["LastVerdict"]) == (run.id, run.verdict)
        assert r["all"] == [x.id for x in service.store.runs("mill1")]
        got = r["byId"][run.id]
        assert got["evaluation"] == EVALUATION[run.verdict] and got["resultState"] == 1
        links = service.store.analysis(run.id).links
        content = {c["key"]: c for c in got["content"]}
        for name, e in links.items():
            assert content[name]["value"] == pytest.approx(e.value)
            assert content[name]["u"] == pytest.approx(e.std)
        assert r["machines"]["mill1"]["identification"]["Manufacturer"] == "Acme"
        # the AQDEF file of the run in the drop folder
        dfq = tmp_path / "spc" / f"mill1_{run.id}.dfq"
        f = read_aqdef(dfq)
        assert {v[0]["K0006"] for v in f.values.values()} == {run.id}
        assert len(f.characteristics) == len(links) + 2
        # the report, downloaded through ResultTransfer by a second client
        code, lines, err = await run_node(service.opcua_url, pki, "--ids", run.id,
                                          "--download", run.id)
        assert code == 0 and lines[-1]["ok"], (lines[-1:], err[-3000:])
        html, _ = service.store.report(run.id)
        pdf = html.with_suffix(".pdf").read_bytes()
        assert lines[-1]["download"]["sha256"] == hashlib.sha256(pdf).hexdigest()
        assert lines[-1]["download"]["head"] == "%PDF-"
    finally:
        if service is not None:
            await service.stop()
        await rig.close()


async def _one_run(tmp: Path, link: dict, ctrl: VirtualController,
                   tolerance: dict | None) -> tuple[Service, str]:
    """One start-of-shift run on a fresh service (the same probing noise every time)."""
    path = await live_config(tmp, link)
    if tolerance is not None:
        doc = yaml.safe_load(path.read_text())
        doc["machines"][0]["tolerances"]["links"] = tolerance
        path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    service = Service(load_daemon_config(path))
    await service.start()
    ctrl.request = False
    ctrl.reseed(NOISE_SEED)
    session = service.sessions["mill1"]
    before = session.run_id
    ctrl.raise_start_request()
    async with asyncio.timeout(180):
        while session.run_id in (None, before) or session.busy:
            await asyncio.sleep(0.05)
    return service, session.run_id


@pytest.mark.peer
@pytest.mark.slow
async def test_live_verdicts_map_to_ok_notok_and_not_decidable(tmp_path):
    """Three runs with the same probing noise (so the same estimate): the plain tolerances
    (PASS → OK), then a fail limit on EX0C between |v| and |v| + k·u (WARN "conformance not
    proven" → NotDecidable), then one below |v| (FAIL → NotOK), read by node-opcua."""
    need_node()
    ctrl = VirtualController(make_truth())
    ctrl.dialect = "fanuc"
    rig = await start_rig("opcua", ctrl)
    ids: list[str] = []
    service: Service | None = None
    try:
        service, rid = await _one_run(tmp_path, rig.link, ctrl, None)
        e = service.store.analysis(rid).links["EX0C"]
        ids.append(rid)
        for fail in (abs(e.value) + 0.5 * e.std, 0.5 * abs(e.value)):
            await service.stop()
            service = None
            service, rid = await _one_run(tmp_path, rig.link, ctrl,
                                          {"EX0C": {"fail": round(fail, 4)}})
            ids.append(rid)
        verdicts = [service.store.run(i).verdict for i in ids]
        again = service.store.analysis(ids[1]).links["EX0C"]
        assert again.value == pytest.approx(e.value, abs=1e-6)  # the same noise, the same v
        assert verdicts == ["PASS", "WARN", "FAIL"], [service.store.verdict(i) for i in ids]
        pki = {"key": tmp_path / "client" / "key.pem", "pem": tmp_path / "client" / "cert.pem"}
        code, lines, err = await run_node(service.opcua_url, pki, "--ids", ",".join(ids))
        assert code == 0 and lines[-1]["ok"], (lines[-1:], err[-3000:])
        assert [lines[-1]["byId"][i]["evaluation"] for i in ids] == [1, 3, 2]
        assert lines[-1]["notDecidable"] == [ids[1]]
    finally:
        if service is not None:
            await service.stop()
        await rig.close()
