"""The daemon's map job against the simulated CNC over OPC UA (real asyncua server and driver):
two small placements, the operator prompt between them answered through the control API (the
artefact moved on the simulator meanwhile), the map fitted and stored next to the reports; a
stop at the prompt; the refusals (an unattended start, a Continue with no prompt, a bad job
file)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import aiohttp
import pytest
import yaml

from benchmarks.rigs.daemon_helpers import write_daemon_yaml
from contracts.map_job import load_map_job
from contracts.yaml_files import ConfigError
from daemon.cli.main import main
from daemon.config import load_daemon_config
from daemon.run.phases import Refused
from daemon.service.service import Service
from daemon.store.journal import Store
from simulators.controller import VirtualController
from simulators.frontends.opcua import OpcUaFrontend
from tests.map_job_helpers import MACHINE, TOUCHES, truth, write_job

TOKEN = "t0k3n-for-tests-0123456789"
@pytest.fixture
async def rig(tmp_path):
    ctrl = VirtualController(truth(0), dialect="fanuc")
    sim = OpcUaFrontend(ctrl, security="none")
    url = await sim.start()
    cfg = load_daemon_config(write_daemon_yaml(
        tmp_path, token=TOKEN, link=f"{{transport: opcua, url: '{url}', security: none}}",
        extra_machine=f"    map_job: {write_job(tmp_path)}"))
    svc = Service(cfg)
    await svc.start()
    yield svc, ctrl, tmp_path
    await svc.stop()
    await sim.stop()


def bearer() -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKEN}"}


async def _status(http, svc) -> dict:
    r = await http.get(svc.hmi_url + "api/status", headers=bearer())
    return (await r.json())["mill1"]


async def _until_prompt(http, svc) -> dict:
    async with asyncio.timeout(120):
        while True:
            st = await _status(http, svc)
            if st["prompt"] is not None:
                return st
            assert st["busy"], f"the run ended before its prompt: {st['state']} {st['reason']}"
            await asyncio.sleep(0.05)


async def _start_map(http, svc) -> str:
    r = await http.post(svc.hmi_url + "api/machines/mill1/start",
                        params={"job": "map", "operator": "Ana Lopez"}, headers=bearer())
    assert r.status == 202, await r.text()
    return (await r.json())["run_id"]


async def test_two_placements_with_a_continue_give_a_journaled_map(rig):
    svc, ctrl, tmp = rig
    async with aiohttp.ClientSession() as http:
        st = await _status(http, svc)
        assert st["map_job"] == {"name": "thesis-map-small", "placements": 2}
        run_id = await _start_map(http, svc)
        st = await _until_prompt(http, svc)
        # the first placement is journaled whole, the machine waits for the operator
        assert st["prompt"]["placement"] == 2 and st["prompt"]["of"] == 2
        assert "balls on the outer rods" in st["prompt"]["text"]
        assert "waiting for the operator to move the artefact to P2" in st["step"]
        store = svc.store
        assert st["done"] == TOUCHES and st["total"] == 2 * TOUCHES
        assert st["eta_s"] is None  # no machine time runs while the operator works
        assert store.run(run_id).reason.startswith("waiting for the operator: move the artefact")
        first = store.hits(run_id)
        assert len(first) == TOUCHES and {h.extra["placement"] for h in first} == {1.0}
        ctrl.move_artefact(truth(1))  # the operator moves the balls
        r = await http.post(svc.hmi_url + "api/machines/mill1/continue",
                            params={"operator": "Ana Lopez", "run_id": run_id},
                            headers=bearer())
        assert r.status == 200, await r.text()
        r = await http.post(svc.hmi_url + "api/machines/mill1/continue", headers=bearer())
        assert r.status == 409  # the prompt was answered: a second Continue has none
        final = await svc.sessions["mill1"].wait()
        listed = await (await http.get(svc.hmi_url + "api/runs", headers=bearer())).json()
    assert final["state"] == "IDLE", final["reason"]
    assert [(r["state"], r["hits"]) for r in listed if r["id"] == run_id] == \
        [("DONE", 2 * TOUCHES)]
    run = store.run(run_id)
    assert run.state == "DONE" and run.hits == 2 * TOUCHES
    assert "map of 2 placements" in run.reason
    hits = store.hits(run_id)
    assert [h.seq for h in hits] == list(range(1, 2 * TOUCHES + 1))  # one run, one sequence
    assert [int(h.extra["placement"]) for h in hits] == [1] * TOUCHES + [2] * TOUCHES
    reports = tmp / "reports"
    doc = json.loads((reports / f"{run_id}.map.json").read_text(encoding="utf-8"))
    assert [p["centres"] for p in doc["placements"]] == [36, 36]
    from contracts.linear_map import load_map
    from daemon.store.map_results import listed

    assert load_map(reports / f"{run_id}.map.json").job.run_id == run_id  # a map file
    journaled = [m for m in listed(store, "mill1") if m.id == run_id]
    assert len(journaled) == 1  # the map results of history, HMI, fleet store, OPC UA
    steps = doc["job"]["operator_steps"]
    assert len(steps) == 1 and steps[0]["placement"] == "P2"
    assert steps[0]["continued_by"] == "Ana Lopez"
    assert steps[0]["continued_at"] >= steps[0]["prompted_at"]
    # the map sees the injected motion errors (thesis_map_demo: 5-20 µm over the strokes)
    assert 5.0 < doc["figures"]["volumetric_max_um"]["value_um"] < 60.0
    assert (reports / f"{run_id}.P1.csv").is_file() and (reports / f"{run_id}.P2.csv").is_file()
    rows = store.db.execute("SELECT action, person, outcome, detail FROM hmi_actions WHERE "
                            "run_id=? ORDER BY id", (run_id,)).fetchall()
    assert [r[0] for r in rows] == ["start", "continue", "continue"]
    # the bearer script's identity, the person it names, the prompt answered
    assert rows[1][1:3] == ("token", "ok")
    assert rows[1][3].startswith("continued by Ana Lopez: move the artefact to placement 2 of 2")
    assert rows[2][2].startswith("refused: mill1: no map placement waits")
    # rumba map takes the job file and the run's logs and fits the same map
    again = tmp / "again.json"
    code = main(["map", "--machine", str(MACHINE), "--job", str(tmp / "map-job.yaml"),
                 "--log", str(reports / f"{run_id}.P1.csv"),
                 "--log", str(reports / f"{run_id}.P2.csv"), "--json", str(again)])
    assert code == 0
    refit = json.loads(again.read_text(encoding="utf-8"))["figures"]["volumetric_max_um"]
    assert refit["value_um"] == pytest.approx(doc["figures"]["volumetric_max_um"]["value_um"],
                                              abs=1e-6)


@pytest.mark.parametrize("source", ["hmi", "CAN panel", "the daemon stopping"])
async def test_a_stop_at_the_prompt_keeps_the_first_placement(rig, source):
    svc, _ctrl, _tmp = rig
    session = svc.sessions["mill1"]
    async with aiohttp.ClientSession() as http:
        run_id = await _start_map(http, svc)
        await _until_prompt(http, svc)
        if source == "hmi":
            r = await http.post(svc.hmi_url + "api/machines/mill1/abort", headers=bearer())
            assert r.status == 200, await r.text()
            st = await r.json()
        elif source == "CAN panel":
            assert await svc.abort("mill1", source)
            st = session.status()
        else:
            assert await session.interrupt(source)
            st = session.status()
        listed = await (await http.get(svc.hmi_url + "api/runs", headers=bearer())).json()
    end = "INTERRUPTED" if source == "the daemon stopping" else "ABORTED"
    assert st["state"] == end and st["prompt"] is None
    assert "waiting for the operator to move the artefact to P2" in st["reason"]
    run = svc.store.run(run_id)
    assert run.state == end and run.hits == TOUCHES  # the first placement's hits kept
    assert [r["state"] for r in listed if r["id"] == run_id] == [end]
    # the machine is free again: a verification run starts
    session = svc.sessions["mill1"]
    session.start("cli")
    await session.abort("cli")


async def test_unattended_starts_refuse_a_map_of_several_placements(rig):
    svc, _ctrl, _tmp = rig
    session = svc.sessions["mill1"]
    for trigger in ("cnc", "rerun"):
        with pytest.raises(Refused, match="2 placements and an operator must move the artefact"):
            session.start(trigger, job="map")
    assert not session.busy
    with pytest.raises(Refused, match="no map placement waits"):
        session.continue_map("someone")


async def test_a_machine_without_a_map_job_refuses_one(tmp_path):
    from benchmarks.rigs.daemon_helpers import thesis_setup
    from daemon.analysis.replay_link import ReplayLink

    setup = thesis_setup()
    store = Store(tmp_path / "j.sqlite")
    from daemon.run.session import Session

    s = Session(setup, ReplayLink([], setup.machine), store, tmp_path / "reports")
    with pytest.raises(Refused, match="no map job configured"):
        s.start("hmi", job="map")
    store.close()


def test_rumba_map_wants_one_log_per_placement_of_the_job(tmp_path, capsys):
    code = main(["map", "--machine", str(MACHINE), "--job", write_job(tmp_path),
                 "--log", str(tmp_path / "p1.csv"), "--json", str(tmp_path / "m.json")])
    err = capsys.readouterr().err
    assert code == 2 and "2 placements (P1, P2), 1 --log given" in err


def test_a_job_file_with_a_bad_key_or_file_is_named(tmp_path):
    path = write_job(tmp_path)
    job = load_map_job(path)
    assert [p.name for p in job.placements] == ["P1", "P2"]
    assert "placement 2 of 2 (P2)" in job.placements[1].prompt(1, 2)
    doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    doc["placements"][1]["artefakt"] = doc["placements"][1].pop("artefact")
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc), encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad.yaml.*placements.1.artefakt"):
        load_map_job(bad)
    doc["placements"][1]["artefact"] = "nowhere.yaml"
    del doc["placements"][1]["artefakt"]
    bad.write_text(yaml.safe_dump(doc), encoding="utf-8")
    with pytest.raises(ConfigError, match=r"placements.1.artefact: file .*nowhere.yaml"):
        load_map_job(bad)


async def test_rumba_verify_map_answers_the_prompt_on_the_terminal(tmp_path, monkeypatch, capsys):
    from daemon.cli.commands import verify_map
    from daemon.cli.commands.verify import verify

    ctrl = VirtualController(truth(0), dialect="fanuc")
    sim = OpcUaFrontend(ctrl, security="none")
    url = await sim.start()
    cfg = write_daemon_yaml(tmp_path, token=TOKEN,
                            link=f"{{transport: opcua, url: '{url}', security: none}}",
                            extra_machine=f"    map_job: {write_job(tmp_path)}")
    entered = []

    async def enter() -> bool:  # the operator moves the balls, then presses Enter
        ctrl.move_artefact(truth(1))
        entered.append(True)
        return True

    monkeypatch.setattr(verify_map, "_enter", enter)
    try:
        code = await verify(str(cfg), "mill1", quiet=True, operator="Ana Lopez", job="map")
    finally:
        await sim.stop()
    out = capsys.readouterr()
    assert code == 0, out.err  # the shipped daemon.yaml's volumetric limit: 200 µm warn
    assert entered == [True]
    assert "move the artefact to placement 2 of 2 (P2)" in out.err
    assert "map (JSON): " in out.out and out.out.strip().endswith(".map.json")
    store = Store(tmp_path / "journal.sqlite")
    try:
        run = store.runs("mill1")[0]
        assert run.state == "DONE" and run.hits == 2 * TOUCHES and run.started_by == "Ana Lopez"
    finally:
        store.close()


def test_a_map_done_is_no_error_verdict_for_notifications_and_mqtt(tmp_path):
    """A map job ends DONE without a verdict of the machine: no ERROR e-mail or webhook, the
    retained MQTT verdict left the last check's; a map job stopped is an ERROR as any run."""
    from types import SimpleNamespace

    from daemon.mqtt.publisher import MachinePublisher
    from daemon.notify.notifier import RunWatcher

    sent: list = []
    notifier = SimpleNamespace(cfg=SimpleNamespace(on=("FAIL", "ERROR")), site="s",
                               notify=sent.append)
    w = RunWatcher(notifier, "mill1")  # type: ignore[arg-type]

    def st(state: str, run_id: str) -> dict:
        return {"state": state, "run_id": run_id, "reason": f"{run_id} {state}",
                "verdict": None, "job": "map", "trigger": "hmi", "link_ok": True, "done": 1,
                "total": 2, "eta_s": None}

    for s in (st("IDLE", ""), st("CAPTURE", "A"), st("IDLE", "A"), st("CAPTURE", "B"),
              st("ABORTED", "B")):
        w.on_status(s)
    assert [(n.run_id, n.status) for n in sent] == [("B", "ERROR")]
    store = Store(tmp_path / "j.sqlite")
    try:
        cfg = SimpleNamespace(queue_max=10, qos=1, root="rumba", site="s")
        pub = MachinePublisher(cfg, "mill1", store)  # type: ignore[arg-type]
        ended: list[str] = []
        pub._verdict = lambda s: ended.append(s["run_id"]) or False  # type: ignore[method-assign]
        for s in (st("CAPTURE", "A"), st("IDLE", "A"), st("CAPTURE", "B"), st("ABORTED", "B")):
            pub.on_status(s)
        assert ended == ["B"]
    finally:
        store.close()


async def test_a_map_of_one_placement_may_start_unattended(tmp_path):
    """Nobody needs to move anything: a CNC start runs a one-placement map job to its end."""
    ctrl = VirtualController(truth(0), dialect="fanuc")
    sim = OpcUaFrontend(ctrl, security="none")
    url = await sim.start()
    job = write_job(tmp_path)
    doc = yaml.safe_load(Path(job).read_text(encoding="utf-8"))
    doc["placements"] = doc["placements"][:1]
    Path(job).write_text(yaml.safe_dump(doc), encoding="utf-8")
    svc = Service(load_daemon_config(write_daemon_yaml(
        tmp_path, token=TOKEN, link=f"{{transport: opcua, url: '{url}', security: none}}",
        extra_machine=f"    map_job: {job}")))
    await svc.start()
    try:
        session = svc.sessions["mill1"]
        run_id = session.start("cnc", job="map")
        final = await session.wait()
    finally:
        await svc.stop()
        await sim.stop()
    assert final["state"] == "IDLE" and final["reason"].startswith("map of 1 placement:")
    assert final["map"]["status"] == "PASS"  # the daemon.yaml's 200 µm warn limit
    store = Store(tmp_path / "journal.sqlite")
    try:
        run = store.run(run_id)
        assert run.state == "DONE" and run.trigger == "cnc" and run.hits == TOUCHES
    finally:
        store.close()
