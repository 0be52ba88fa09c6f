"""The OPC UA results of every machine of a shop from the PostgreSQL fleet
store (``rumba fleet --opcua``): one endpoint; node-opcua reads each machine's results with the
ResultEvaluation of its verdicts, and a run drained to the store later raises its
ResultReadyEvent (the server follows the store)."""

from __future__ import annotations

import asyncio

import pytest
import pytest_asyncio
from asyncua import Client, ua

from benchmarks.rigs.opcua_results_helpers import (
    CLIENT_URI,
    PASSWORD,
    USER,
    analysis,
    fill,
    make_pki,
    server_config,
)
from daemon.opcua.server import ResultServer
from daemon.opcua.source import FleetSource
from daemon.store import report_jobs
from daemon.store.drain import Drainer
from daemon.store.journal import Store
from daemon.store.pg import PgStore
from tests.fleet_helpers import fresh_db, start_postgres
from tests.test_opcua_results import need_node, run_node

EVALUATION = {"run-pass": 1, "run-fail": 2, "run-nd": 3, "run-warn": 1, "run-aborted": 0}


@pytest.fixture(scope="module")
def pg():
    server = start_postgres()
    yield server
    server.close()


class Events:
    def __init__(self) -> None:
        self.got: asyncio.Queue = asyncio.Queue()

    def event_notification(self, e: object) -> None:
        self.got.put_nowait(e)


@pytest_asyncio.fixture
async def fleet(pg, tmp_path):
    need_node()
    dsn = fresh_db(pg)
    store = Store(tmp_path / "j.sqlite")
    drainer = Drainer(store, dsn)  # before the first write: its change capture sees them all
    fill(store)  # mill1: the verdict cases
    store.new_run("m2-1", "mill2", "cnc", state="DONE")
    store.save_analysis("m2-1", analysis(1))
    store.save_verdict("m2-1", "PASS", [], [], "PASS")
    store.set_state("m2-1", "DONE")
    await drainer.drain()
    source = FleetSource(await PgStore.connect(dsn, migrate=False))
    cert, key, pem = await make_pki(tmp_path)
    srv = ResultServer(server_config(tmp_path, cert.parent), source, await source.machines())
    url = await srv.start()
    srv.follow(0.1)
    yield {"url": url, "store": store, "drainer": drainer, "srv": srv,
           "pki": {"cert": cert, "key": key, "pem": pem}}
    await srv.stop()
    await source.pg.close()
    await drainer.stop()
    store.close()


@pytest.mark.peer
async def test_one_endpoint_serves_every_machine_of_the_fleet_store(fleet):
    code, lines, err = await run_node(fleet["url"], fleet["pki"], "--machine", "mill1")
    assert code == 0 and lines[-1]["ok"], (lines[-1:], err[-3000:])
    r = lines[-1]
    assert sorted(r["machines"]) == ["mill1", "mill2"]
    assert r["all"] == ["run-aborted", "run-warn", "run-nd", "run-fail", "run-pass"]
    for rid, ev in EVALUATION.items():
        assert r["byId"][rid]["evaluation"] == ev, rid
    assert r["notDecidable"] == ["run-nd"]
    assert r["byId"]["run-pass"]["content"][1]["key"] == "EX0C"
    code, lines, err = await run_node(fleet["url"], fleet["pki"], "--machine", "mill2")
    assert code == 0 and lines[-1]["all"] == ["m2-1"] and lines[-1]["latest"]["evaluation"] == 1


@pytest.mark.peer
async def test_a_run_reaching_the_store_raises_its_result_ready_event(fleet):
    c = Client(fleet["url"], timeout=10)
    c.application_uri = CLIENT_URI
    await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{fleet['pki']['cert']},"
                                f"{fleet['pki']['key']}")
    c.set_user(USER)
    c.set_password(PASSWORD)
    async with c:
        await c.load_data_type_definitions()
        ns = await c.get_namespace_array()
        res = ns.index("http://opcfoundation.org/UA/Machinery/Result/")
        handler = Events()
        sub = await c.create_subscription(50, handler)
        await sub.subscribe_events(c.nodes.server, c.get_node(ua.NodeId(1002, res)))
        store = fleet["store"]

        def ended(run_id: str, status: str, checks: list) -> None:
            """A run's end as a daemon journals it: judged, its report job begun, DONE."""
            store.new_run(run_id, "mill2", "cnc", state="WRITE-BACK")
            store.save_analysis(run_id, analysis(2))
            store.save_verdict(run_id, status, [], checks, status)
            report_jobs.begin(store, run_id)
            store.set_state(run_id, "DONE")

        ended("m2-2", "FAIL", [{"status": "FAIL", "limit": "x"}])
        await fleet["drainer"].drain()  # the run first, its report after it
        html = fleet["store"].path.parent / "m2-2.html"
        html.write_text("<html></html>")
        html.with_suffix(".pdf").write_bytes(b"%PDF-1.4\n")
        report_jobs.written(store, "m2-2", html, html.with_suffix(".json"))
        await fleet["drainer"].drain()
        e = await asyncio.wait_for(handler.got.get(), 30)
        assert e.Result.ResultMetaData.ResultId == "m2-2"
        # announced once its report job ended (the report reached the store), not when the
        # run did
        assert e.Result.ResultMetaData.HasTransferableDataOnFile
        assert int(e.Result.ResultMetaData.ResultEvaluation) == 2
        assert e.SourceName == "mill2"
        # a report job that failed: announced at once (no fixed wait), the reason told
        ended("m2-3", "PASS", [])
        await fleet["drainer"].drain()
        report_jobs.failed(store, "m2-3", "OSError: [Errno 28] No space left on device")
        await fleet["drainer"].drain()
        e = await asyncio.wait_for(handler.got.get(), 30)
        assert e.Result.ResultMetaData.ResultId == "m2-3"
        assert not e.Result.ResultMetaData.HasTransferableDataOnFile
        assert "report not written: OSError: [Errno 28] No space left on device" in \
            e.Message.Text, e.Message.Text
        assert handler.got.empty()  # m2-2 once, m2-3 once

def test_a_bad_opcua_file_stops_rumba_fleet_with_one_line(tmp_path, capsys):
    from daemon.cli.main import main as cli_main

    token = tmp_path / "token"
    token.write_text("a-fleet-token-0123456789")
    token.chmod(0o600)
    bad = tmp_path / "opcua.yaml"
    bad.write_text("host: 0.0.0.0\ntrusted_dir: t\nusers: {q: pw}\nnodesets_dir: n\n")
    code = cli_main(["fleet", "--store", "postgresql://rumba@127.0.0.1/fleet", "--token-file",
                     str(token), "--opcua", str(bad)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert f"{bad}: <top>: host 0.0.0.0 is not loopback" in err
