"""Set-up for the OPC UA results server tests: a journal with runs of known verdicts,
a client certificate in the server's trust list, a user with a password file, and the config."""

from __future__ import annotations

import time
from pathlib import Path

from contracts.opcua_certs import ensure_certificate
from daemon.analysis.judge import Check
from daemon.analysis.result import Analysis, LinkError, VolumetricPoint
from daemon.opcua.config import NODESETS, IdentificationFile, OpcUaServerConfig
from daemon.store.journal import Store

ROOT = Path(__file__).resolve().parents[2]
NODESETS_DIR = ROOT / ".peers" / "node" / "node_modules" / "node-opcua-nodesets" / "nodesets"
USER, PASSWORD = "quality", "s3cret-password-for-tests"
CLIENT_URI = "urn:rumba-cnc:test-client"
T0 = time.time() - 86400 * 30

IDENT = IdentificationFile(manufacturer="Acme Machine Tools", model="FiveAx 650",
                           serial_number="SN-4711", year_of_construction=2019,
                           location="Hall 2")

# verdicts and the checks behind them: PASS, FAIL, and a WARN whose only cause is the guard
# band k·u reaching the fail limit (not decidable), and a WARN over a warning limit only
CASES = {
    "run-pass": ("PASS", []),
    "run-fail": ("FAIL", [Check("EX0C", 320.0, 2.0, "µm", "FAIL", "|value| > fail 300 µm")]),
    "run-nd": ("WARN", [Check("EX0C", 146.0, 1.5, "µm", "WARN",
                              "|value| + 2u ≥ fail 148 µm (conformance not proven)")]),
    "run-warn": ("WARN", [Check("EX0C", 160.0, 1.0, "µm", "WARN", "|value| > warn 150 µm")]),
}


def analysis(k: int) -> Analysis:
    return Analysis(machine="thesis", links={
        "EX0C": LinkError(12.5 + k, 0.4, "um"), "EB0C": LinkError(-7.25, 1.1, "urad")},
        volumetric=(VolumetricPoint(pose=0, ball="A", error_um=(3.0, 4.0, 0.0),
                                    error_after_links_um=(0.3, 0.4, 0.0)),))


def fill(store: Store, machine: str = "mill1", extra: int = 0) -> None:
    """The four CASES (oldest first), then ``extra`` PASS runs, then one ABORTED run."""
    with store.transaction():
        for k, (rid, (verdict, checks)) in enumerate(CASES.items()):
            store.new_run(rid, machine, "hmi", started_at=T0 + 3600 * k, state="DONE",
                          artefact="thesis-4ball", plan="thesis_ch3_7poses")
            store.save_analysis(rid, analysis(k))
            store.save_verdict(rid, verdict, [], [c.as_dict() for c in checks], verdict)
            store.set_state(rid, "DONE")
        for k in range(extra):
            rid = f"bulk-{k:05d}"
            store.new_run(rid, machine, "cnc", started_at=T0 + 7200 + 60 * k, state="DONE")
            store.save_analysis(rid, analysis(k))
            store.save_verdict(rid, "PASS" if k % 3 else "FAIL", [], [], "")
        store.new_run("run-aborted", machine, "hmi", started_at=T0 + 86400 * 20)
        store.set_state("run-aborted", "ABORTED", "stopped at the HMI")


async def make_pki(tmp: Path) -> tuple[Path, Path, Path]:
    """A client certificate (DER) + key (PEM) and its PEM copy for node-opcua."""
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    cert, key = tmp / "trusted" / "client_cert.der", tmp / "client" / "key.pem"
    await ensure_certificate(cert, key, CLIENT_URI, server=False)
    pem = tmp / "client" / "cert.pem"
    pem.write_bytes(x509.load_der_x509_certificate(cert.read_bytes()).public_bytes(Encoding.PEM))
    return cert, key, pem


def server_config(tmp: Path, trusted: Path) -> OpcUaServerConfig:
    return OpcUaServerConfig("127.0.0.1", 0, tmp / "server-pki", trusted,
                             {USER: PASSWORD}, tuple(NODESETS_DIR / n for n in NODESETS),
                             {"mill1": IDENT})
