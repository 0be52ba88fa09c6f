"""The daemon's OPC UA results server read by an independent client: node-opcua
(tests/peers/opcua_results_client.js) with the official companion nodesets checks the type of
every node, reads identification and state, calls GetLatestResult / GetResultById /
GetResultIdListFiltered, receives the ResultReadyEvent of a run that ends and downloads its
report through ResultTransfer; wrong credentials, no security and an untrusted certificate are
refused. ResultEvaluation matches the verdict: PASS → OK, FAIL → NotOK, a WARN whose only cause
is the guard band k·u reaching the fail limit → NotDecidable, a WARN over a warning limit → OK."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua

from benchmarks.rigs.opcua_results_helpers import (
    CLIENT_URI,
    NODESETS_DIR,
    PASSWORD,
    USER,
    analysis,
    fill,
    make_pki,
    server_config,
)
from contracts.opcua_certs import ensure_certificate
from daemon.opcua.server import ResultServer
from daemon.store.journal import Store

ROOT = Path(__file__).resolve().parents[1]
NODE_SCRIPT = ROOT / "tests" / "peers" / "opcua_results_client.js"
NODE_MODULES = ROOT / ".peers" / "node" / "node_modules"
EVALUATION = {"run-pass": 1, "run-fail": 2, "run-nd": 3, "run-warn": 1, "run-aborted": 0}


def need_node() -> str:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node not installed")
    if not (NODE_MODULES / "node-opcua").is_dir() or not NODESETS_DIR.is_dir():
        pytest.skip("node-opcua / node-opcua-nodesets not installed "
                    "(bash .ci/install-peers.sh node-opcua)")
    return node


async def run_node(url: str, pki: dict[str, Path], *extra: str, on_subscribed: Any = None,
                   user: str = USER, password: str = PASSWORD,
                   cert: Path | None = None, key: Path | None = None,
                   timeout_s: float = 180) -> tuple[int, list[dict[str, Any]], str]:
    args = [need_node(), str(NODE_SCRIPT), url, "--cert", str(cert or pki["pem"]),
            "--key", str(key or pki["key"]), "--app-uri", CLIENT_URI, "--user", user,
            "--password", password, *extra]
    proc = await asyncio.create_subprocess_exec(*args, stdout=asyncio.subprocess.PIPE,
                                                stderr=asyncio.subprocess.PIPE,
                                                env={**os.environ})
    lines: list[dict[str, Any]] = []
    try:
        assert proc.stdout is not None and proc.stderr is not None
        async with asyncio.timeout(timeout_s):
            while line := await proc.stdout.readline():
                lines.append(json.loads(line))
                if lines[-1].get("event") == "subscribed" and on_subscribed is not None:
                    await on_subscribed()
            err = (await proc.stderr.read()).decode()
            await proc.wait()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode is not None
    return proc.returncode, lines, err


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def served(tmp_path_factory):
    need_node()
    tmp = tmp_path_factory.mktemp("results")
    store = Store(tmp / "journal.sqlite")
    fill(store)
    html = tmp / "reports" / "run-pass.html"
    html.parent.mkdir()
    html.write_text("<html>report</html>", encoding="utf-8")
    pdf = html.with_suffix(".pdf")
    pdf.write_bytes(b"%PDF-1.4\n" + os.urandom(200_000))  # several Read calls of 64 KiB
    store.save_report("run-pass", html, html.with_suffix(".json"))
    cert, key, pem = await make_pki(tmp)
    srv = ResultServer(server_config(tmp, cert.parent), store, ["mill1"])
    url = await srv.start()
    yield {"srv": srv, "store": store, "url": url, "tmp": tmp, "pdf": pdf,
           "pki": {"cert": cert, "key": key, "pem": pem}}
    await srv.stop()
    store.close()


@pytest.mark.peer
@pytest.mark.asyncio(loop_scope="module")
async def test_node_opcua_checks_types_calls_methods_and_gets_the_event(served):
    store, srv = served["store"], served["srv"]
    listener = srv.listener("mill1")

    async def end_a_run() -> None:
        # a run starts, makes progress and ends FAIL: journal first, then the session's status
        listener({"state": "CAPTURE", "run_id": "run-live", "done": 3, "total": 12,
                  "link_ok": True})
        store.new_run("run-live", "mill1", "cnc", state="DONE")
        store.save_analysis("run-live", analysis(9))
        store.save_verdict("run-live", "FAIL", ["EX0C too large"],
                           [{"status": "FAIL", "limit": "|value| > fail 300 µm"}], "FAIL")
        store.set_state("run-live", "DONE")
        listener({"state": "IDLE", "run_id": "run-live", "done": 12, "total": 12,
                  "link_ok": True})

    code, lines, err = await run_node(served["url"], served["pki"], "--wait-event",
                                      "--download", "run-pass", on_subscribed=end_a_run)
    assert code == 0 and lines[-1]["ok"], (lines, err[-3000:])
    r = lines[-1]
    assert r["checked"] == [f"mill1/{n}" for n in ("Identification", "MachineryBuildingBlocks",
                                                   "MachineryItemState", "ResultManagement",
                                                   "ResultTransfer")]
    ident = r["machines"]["mill1"]["identification"]
    assert (ident["Manufacturer"], ident["Model"], ident["SerialNumber"],
            ident["YearOfConstruction"], ident["ComponentName"]) == (
        "Acme Machine Tools", "FiveAx 650", "SN-4711", 2019, "mill1")
    # the event of the run that ended, with its result
    assert r["event"]["result"]["resultId"] == "run-live"
    assert r["event"]["result"]["evaluation"] == 2 and r["event"]["result"]["resultState"] == 1
    assert ["State", "CAPTURE"] in r["seen"] and ["DoneTouches", 3] in r["seen"]
    assert ["MachineryItemState", "Executing"] in r["seen"], json.dumps(r["seen"])
    assert (r["after"]["LastResultId"], r["after"]["LastVerdict"],
            r["after"]["LastResultEvaluation"]) == ("run-live", "FAIL", 2)
    assert r["latest"]["resultId"] == "run-live" and r["latest"]["error"] == 0
    assert r["all"] == ["run-live", "run-aborted", "run-warn", "run-nd", "run-fail", "run-pass"]
    for rid, ev in EVALUATION.items():
        assert r["byId"][rid]["evaluation"] == ev, rid
        assert r["byId"][rid]["error"] == 0
    assert r["byId"]["run-aborted"]["resultState"] == 3  # Aborted
    assert r["notDecidable"] == ["run-nd"] and r["ndErr"] == 0
    # link errors with units (UNECE codes 4H µm, B97 µrad) and standard uncertainties
    content = {c["key"]: c for c in r["byId"]["run-pass"]["content"]}
    assert content["EX0C"] == {"key": "EX0C", "value": 12.5, "u": 0.4, "unit": "µm",
                               "unitId": 0x3448}
    assert content["EB0C"]["unit"] == "µrad" and content["EB0C"]["unitId"] == 0x423937
    assert content["VD_MAX"]["value"] == pytest.approx(5.0) and content["VD_MAX"]["u"] is None
    pdf = served["pdf"].read_bytes()
    assert r["download"] == {"bytes": len(pdf), "size": len(pdf), "fileType": True,
                             "closed": True, "sha256": hashlib.sha256(pdf).hexdigest(),
                             "head": "%PDF-"}
    assert served["srv"].machines["mill1"].transfer.open == {}  # Close removed the file node


@pytest.mark.peer
@pytest.mark.asyncio(loop_scope="module")
@pytest.mark.parametrize("case", ["wrong-password", "no-security", "untrusted-certificate"])
async def test_node_opcua_is_refused(served, case):
    kw: dict[str, Any] = {}
    extra: list[str] = []
    if case == "wrong-password":
        kw["password"] = "not-the-password-at-all"
    elif case == "no-security":
        extra = ["--security", "none"]
    else:
        other = served["tmp"] / "stranger"
        await ensure_certificate(other / "cert.der", other / "key.pem", CLIENT_URI,
                                 server=False)
        from cryptography import x509
        from cryptography.hazmat.primitives.serialization import Encoding

        pem = other / "cert.pem"
        pem.write_bytes(x509.load_der_x509_certificate(
            (other / "cert.der").read_bytes()).public_bytes(Encoding.PEM))
        kw.update(cert=pem, key=other / "key.pem")
    code, lines, err = await run_node(served["url"], served["pki"], *extra, timeout_s=60, **kw)
    assert code == 2 and lines and not lines[-1]["ok"], (lines, err[-2000:])
    assert "machines" not in lines[-1]


async def _client(served: dict[str, Any]) -> Client:
    c = Client(served["url"], timeout=10)
    c.application_uri = CLIENT_URI
    await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{served['pki']['cert']},"
                                f"{served['pki']['key']}")
    c.set_user(USER)
    c.set_password(PASSWORD)
    return c


@pytest.mark.peer  # the official nodesets come with node-opcua's install
@pytest.mark.asyncio(loop_scope="module")
async def test_unknown_ids_filters_and_limits(served):
    c = await _client(served)
    async with c:
        ns = await c.get_namespace_array()
        res, idx = (ns.index("http://opcfoundation.org/UA/Machinery/Result/"),
                    ns.index("urn:rumba-cnc:results"))
        rm = c.get_node(ua.NodeId("mill1.ResultManagement", idx))
        t = ua.Variant(1000.0, ua.VariantType.Double)
        out = await rm.call_method(f"{res}:GetResultById", ua.Variant("no-such-run"), t)
        assert out[2] == -1
        out = await rm.call_method(f"{res}:GetResultById", ua.Variant("../bad id"), t)
        assert out[2] == -1

        def flt(field: str, op: ua.FilterOperator, value: Any) -> ua.Variant:
            el = ua.ContentFilterElement(FilterOperator=op, FilterOperands=[
                ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName("ResultMetaData", res),
                                                      ua.QualifiedName(field, res)],
                                          AttributeId=ua.AttributeIds.Value),
                ua.LiteralOperand(Value=ua.Variant(value))])
            return ua.Variant(ua.ContentFilter(Elements=[el]))

        async def ids(f: ua.Variant, n: int = 0) -> tuple[list[str], int]:
            out = await rm.call_method(f"{res}:GetResultIdListFiltered", f,
                                       ua.Variant([], ua.VariantType.ExtensionObject),
                                       ua.Variant(n, ua.VariantType.UInt32), t)
            return out[1], out[2]

        got, err = await ids(flt("ResultEvaluation", ua.FilterOperator.Equals, 2))
        assert err == 0 and got[-1] == "run-fail" and set(got) <= {"run-fail", "run-live"}
        assert await ids(flt("ResultEvaluation", ua.FilterOperator.Equals, 3)) == (["run-nd"], 0)
        assert await ids(flt("ResultState", ua.FilterOperator.Equals, 3)) == (
            ["run-aborted"], 0)
        got, err = await ids(flt("ResultEvaluation", ua.FilterOperator.GreaterThan, 0), 2)
        assert err == 0 and len(got) == 2
        assert await ids(flt("Temperature", ua.FilterOperator.Equals, 3)) == ([], -3)
