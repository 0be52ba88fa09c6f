"""`rumba run`: bad configuration is one line and exit 2, kill -9 mid-run leaves an INTERRUPTED
run with its hits and the restarted daemon runs again, the shipped daemon.yaml is valid
(verify and history: test_verify_history_cli.py)."""

from __future__ import annotations

import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.rigs.daemon_helpers import ROOT, write_daemon_yaml
from tests.cli_helpers import free_port, run_cli

# ------------------------------------------------------------------------- bad configuration


@pytest.mark.parametrize(("edit", "expect"), [
    (lambda t: t.replace("touch_timeout_s: 30", "touch_timeout_s: 30\n    colour: red"),
     r"machines\.0\.colour: unknown key"),
    (lambda t: t.replace("touch_timeout_s: 30", "touch_timeout_s: soon"),
     r"machines\.0\.touch_timeout_s: Input should be a valid number"),
    (lambda t: t.replace("dialect: fanuc", "dialect: mazak"),
     r"machines\.0\.dialect: Input should be 'fanuc', 'haas', 'siemens'"),
    (lambda t: t.replace("security: none", "security: Basic256Sha256_SignAndEncrypt, "
                         "certificate: nope.der, private_key: nope.pem"),
     r"machines\.0\.link\.certificate: file .*nope\.der not found"),
    (lambda t: t.replace("port: 0,", "port: 0, tls: {cert: no.crt, key: no.key},"),
     r"hmi\.tls\.cert: file .*no\.crt not found"),
    (lambda t: t.replace("host: 127.0.0.1,", "host: 0.0.0.0,"),
     r"hmi: host 0\.0\.0\.0 is not loopback; set allow_remote"),
    (lambda t: t.replace("default_rotation_urad:", "links: {EX0B: {fail: 5}}\n"
                         "      default_rotation_urad:"),
     r"tolerances\.links\.EX0B: not identifiable with plan"),
])
def test_bad_config_is_one_line_exit_2(tmp_path, capsys, edit, expect):
    path = write_daemon_yaml(tmp_path)
    path.write_text(edit(path.read_text()))
    code, out, err = run_cli(["run", "--config", str(path)], capsys)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith(f"error: {path}"), err
    import re
    assert re.search(expect, err), err


def test_token_file_must_be_private(tmp_path, capsys):
    path = write_daemon_yaml(tmp_path)
    tok = tmp_path / "hmi.token"
    tok.write_text("s3cret-token-0123456789\n")
    tok.chmod(0o644)
    path.write_text(path.read_text().replace("token: t0k3n-for-tests-0123456789",
                                             f"token_file: {tok}"))
    code, _, err = run_cli(["run", "--config", str(path)], capsys)
    assert code == 2 and "readable by others (mode 0644); chmod 600" in err
    tok.chmod(0o600)
    code, out, _ = run_cli(["run", "--config", str(path), "--check"], capsys)
    assert code == 0 and "OK (1 machines: mill1)" in out


def test_unreachable_controller_is_one_line_exit_2(tmp_path, capsys):
    port = free_port()  # nothing listens there
    path = write_daemon_yaml(tmp_path, link=f"{{transport: opcua, url: 'opc.tcp://127.0.0.1:"
                                            f"{port}', security: none, connect_timeout_s: 1}}")
    code, _out, err = run_cli(["run", "--config", str(path)], capsys)
    assert code == 2 and err.count("\n") == 1
    assert err.startswith(f"error: machine mill1: controller unreachable: opcua opc.tcp://"
                          f"127.0.0.1:{port}")


def test_hmi_port_in_use_is_one_line_exit_2(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        path = write_daemon_yaml(tmp_path)
        path.write_text(path.read_text().replace("port: 0", f"port: {port}"))
        p = subprocess.run([sys.executable, "-m", "tests.replay_daemon", str(path), "0"],
                           cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and p.stdout == ""
    assert p.stderr.strip().splitlines()[-1] == (
        f"error: {path}: hmi: cannot listen on 127.0.0.1:{port}: address already in use")


# ------------------------------------------------------------------------------- kill -9


def _journal(db: Path) -> list[tuple]:
    con = sqlite3.connect(db)
    try:
        return con.execute("SELECT r.id, r.state, r.reason, r.verdict, (SELECT COUNT(*) FROM "
                           "hits h WHERE h.run_id = r.id) FROM runs r ORDER BY started_at"
                           ).fetchall()
    except sqlite3.OperationalError:
        return []
    finally:
        con.close()


def _wait(pred, timeout_s: float = 60.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(0.05)
    raise AssertionError("timed out")


@pytest.mark.slow
def test_kill_9_mid_run_then_restart(tmp_path):
    """The same through the test-only ReplayLink (no simulator): quick to debug."""
    path = write_daemon_yaml(tmp_path)
    db = tmp_path / "journal.sqlite"
    cmd = [sys.executable, "-m", "tests.replay_daemon", str(path), "0.02"]
    d1 = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                          text=True)
    try:
        _wait(lambda: (j := _journal(db)) and j[0][4] >= 20)
        os.kill(d1.pid, signal.SIGKILL)
        d1.wait()
    finally:
        if d1.poll() is None:
            d1.kill()
    before = _journal(db)
    assert len(before) == 1 and before[0][1] == "CAPTURE"
    first, kept = before[0][0], before[0][4]
    d2 = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                          text=True)
    try:
        banner = [d2.stdout.readline() for _ in range(3)]
        assert f"rumba: marked interrupted: {first}\n" in banner
        runs = _wait(lambda: (j := _journal(db)) and len(j) == 2 and j[1][1] == "DONE" and j,
                     timeout_s=90)
        assert runs[0][:2] == (first, "INTERRUPTED") and runs[0][4] == kept
        assert "during CAPTURE" in runs[0][2] and f"{kept} hits kept" in runs[0][2]
        assert runs[1][3] == "PASS" and runs[1][4] == 140
        d2.send_signal(signal.SIGTERM)
        assert d2.wait(timeout=30) == 0
    finally:
        if d2.poll() is None:
            d2.kill()
            d2.wait()


@pytest.mark.slow
async def test_kill_9_with_simulated_cnc_over_opcua(tmp_path):
    """The real path: simulated CNC (asyncua server, SignAndEncrypt) in this process, `rumba run`
    in a subprocess. kill -9 mid-run; the CNC keeps its start request raised, so the restarted
    daemon marks the run INTERRUPTED (hits intact), stops the leftover program and runs again."""
    import asyncio
    import shutil

    from benchmarks.rigs.daemon_helpers import CONFIG
    from contracts.opcua_certs import ensure_certificate
    from simulators.controller import VirtualController
    from simulators.frontends.opcua import OpcUaFrontend
    from simulators.truth import TruthModel

    pki = tmp_path / "pki"
    await ensure_certificate(pki / "client/cert.der", pki / "client/key.pem",
                             "urn:rumba-cnc:daemon", server=False)
    (pki / "trusted").mkdir()
    shutil.copy(pki / "client/cert.der", pki / "trusted/daemon.der")
    truth = TruthModel.from_files(CONFIG / "machines/thesis_wcbxfzyt.yaml",
                                  CONFIG / "artefacts/thesis_4ball.yaml",
                                  CONFIG / "errors/thesis_tableB2.yaml")
    ctrl = VirtualController(truth, time_scale=0.05, dialect="fanuc")
    sim = OpcUaFrontend(ctrl, cert_dir=pki / "server", users={"rumba": "pw-0123456789"},
                        trusted_client_certs=[pki / "trusted"])
    url = await sim.start()
    link = (f"{{transport: opcua, url: '{url}', certificate: {pki / 'client/cert.der'}, "
            f"private_key: {pki / 'client/key.pem'}, server_certificate: "
            f"{sim.server_certificate}, user: {{name: rumba, password: pw-0123456789}}}}")
    path = write_daemon_yaml(tmp_path, link=link)
    db = tmp_path / "journal.sqlite"
    cmd = [sys.executable, "-m", "daemon.cli", "run", "--config", str(path)]

    async def wait(pred, timeout_s=60.0):
        async with asyncio.timeout(timeout_s):
            while not (v := pred()):
                await asyncio.sleep(0.05)
            return v

    d1 = await asyncio.create_subprocess_exec(*cmd, cwd=ROOT, stdout=asyncio.subprocess.PIPE,
                                              stderr=asyncio.subprocess.DEVNULL)
    d2 = None
    try:
        ctrl.raise_start_request()
        await wait(lambda: (j := _journal(db)) and j[0][4] >= 20)
        d1.kill()
        await d1.wait()
        (first, state, _, _, kept), = _journal(db)
        assert state == "CAPTURE" and 20 <= kept < 140
        d2 = await asyncio.create_subprocess_exec(*cmd, cwd=ROOT,
                                                  stdout=asyncio.subprocess.PIPE,
                                                  stderr=asyncio.subprocess.DEVNULL)
        runs = await wait(lambda: (j := _journal(db)) and len(j) == 2 and j[1][1] == "DONE"
                          and j, timeout_s=120)
        assert runs[0][:2] == (first, "INTERRUPTED") and runs[0][4] == kept
        assert runs[1][4] == 140 and runs[1][3] in ("PASS", "WARN")
        await wait(lambda: ctrl.done and ctrl.verdict)
        assert ctrl.verdict in (1, 2)  # the verdict arrived on the CNC side
        d2.terminate()
        assert await asyncio.wait_for(d2.wait(), 30) == 0
    finally:
        for d in (d1, d2):
            if d is not None and d.returncode is None:
                d.kill()
                await d.wait()
        await sim.stop()


def test_shipped_daemon_yaml_is_valid():
    """config/daemon.yaml (the documented shop-PC example) passes the schema, its link section
    the transport's schema, and its tolerance names are identifiable on its machine and plan."""
    import yaml

    from contracts.setup_files import load_artefact, load_machine, load_plan
    from daemon.config import config_from_dict
    from daemon.machines.setup import _check_identifiable
    from drivers.registry import link_config

    path = ROOT / "config/daemon.yaml"
    df = config_from_dict(yaml.safe_load(path.read_text()), path)
    m = df.machines[0]
    assert link_config(m.link).security == "Basic256Sha256_SignAndEncrypt"
    assert df.hmi.host == "127.0.0.1" and df.store.synchronous == "FULL"
    local = {k: ROOT / "config" / Path(getattr(m, k)).relative_to("/etc/rumba")
             for k in ("machine", "artefact", "plan")}
    machine, _ = load_machine(local["machine"])
    _check_identifiable(machine, load_artefact(local["artefact"]), load_plan(local["plan"]),
                        m.tolerances.links, "daemon.yaml")
