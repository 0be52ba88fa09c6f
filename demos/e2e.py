"""End-to-end demo: the simulated CNC (OPC UA, Basic256Sha256 SignAndEncrypt + user/password)
and the daemon (`rumba run`, a separate process) on free loopback ports; the CNC raises its
start-of-shift request, the daemon runs the thesis annex-B plan, and the verdict comes back.

``python -m demos.e2e [--time-scale S] [--out DIR]`` prints the verdict and report path.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import secrets
import shutil
import sys
import tempfile
import time
from pathlib import Path

import aiohttp

from contracts.jobs import VERDICT_CODES

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config"
VERDICT_NAMES = {code: name for name, code in VERDICT_CODES.items()}
MACHINE, ARTEFACT = "machines/thesis_wcbxfzyt.yaml", "artefacts/thesis_4ball.yaml"
PLAN, ERRORS = "plans/shift_start_14poses.yaml", "errors/thesis_tableB2.yaml"


def _daemon_yaml(work: Path, url: str, pki: Path, server_cert: Path, token_file: Path) -> str:
    return f"""# written by demos/e2e.py
store: {{path: {work / 'journal.sqlite'}}}
reports_dir: {work / 'reports'}
hmi: {{host: 127.0.0.1, port: 0, token_file: {token_file}}}
machines:
  - name: demo-hmc
    machine: {CONFIG / MACHINE}
    artefact: {CONFIG / ARTEFACT}
    plan: {CONFIG / PLAN}
    dialect: fanuc
    link:
      transport: opcua
      url: '{url}'
      security: Basic256Sha256_SignAndEncrypt
      certificate: {pki / 'client/cert.der'}
      private_key: {pki / 'client/key.pem'}
      server_certificate: {server_cert}
      user: {{name: rumba, password_env: RUMBA_DEMO_OPCUA_PASSWORD}}
    touch_timeout_s: 60
    tolerances:
      default_rotation_urad: {{warn: 30, fail: 60, drift_warn: 8, drift_fail: 15}}
      default_translation_um: {{warn: 150, fail: 250}}
      volumetric_max_um: {{warn: 150, fail: 250}}
      residual_rms_um: 5
      run_drift_um: 8
"""


async def _hmi(stdout: asyncio.StreamReader, timeout_s: float) -> str:
    """Read the daemon's banner until it says where the HMI listens."""
    async with asyncio.timeout(timeout_s):
        while True:
            line = (await stdout.readline()).decode()
            if not line:
                raise RuntimeError("the daemon exited during startup")
            print(f"  daemon: {line.rstrip()}")
            if line.startswith("rumba: HMI at "):
                return line.split("rumba: HMI at ", 1)[1].strip()


async def demo(time_scale: float, work: Path) -> int:
    from contracts.opcua_certs import ensure_certificate
    from simulators.controller import VirtualController
    from simulators.frontends.opcua import OpcUaFrontend
    from simulators.truth import TruthModel

    t0 = time.monotonic()
    pki = work / "pki"
    await ensure_certificate(pki / "client/cert.der", pki / "client/key.pem",
                             "urn:rumba-cnc:daemon", server=False)
    (pki / "trusted").mkdir(parents=True, exist_ok=True)
    shutil.copy(pki / "client/cert.der", pki / "trusted/daemon.der")
    password = secrets.token_urlsafe(16)
    truth = TruthModel.from_files(CONFIG / MACHINE, CONFIG / ARTEFACT, CONFIG / ERRORS)
    ctrl = VirtualController(truth, time_scale=time_scale, dialect="fanuc")
    sim = OpcUaFrontend(ctrl, cert_dir=pki / "server", users={"rumba": password},
                        trusted_client_certs=[pki / "trusted"])
    url = await sim.start()
    print(f"simulated CNC (OPC UA, SignAndEncrypt) at {url}; errors {ERRORS}")
    token_file = work / "hmi.token"
    token = secrets.token_urlsafe(24)
    token_file.write_text(token)
    token_file.chmod(0o600)
    cfg = work / "daemon.yaml"
    cfg.write_text(_daemon_yaml(work, url, pki, sim.server_certificate, token_file))
    env = {**os.environ, "RUMBA_DEMO_OPCUA_PASSWORD": password}
    daemon = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "daemon.cli", "run", "--config", str(cfg), cwd=ROOT, env=env,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
    try:
        hmi = await _hmi(daemon.stdout, 60)
        print(f"daemon up ({time.monotonic() - t0:.1f} s); the CNC raises its start-of-shift "
              "request")
        ctrl.raise_start_request()
        async with asyncio.timeout(240):
            while not (ctrl.done and ctrl.verdict):
                await asyncio.sleep(0.1)
        verdict = VERDICT_NAMES.get(int(ctrl.verdict), str(ctrl.verdict))
        async with aiohttp.ClientSession(
                headers={"Authorization": f"Bearer {token}"}) as http, \
                http.get(hmi + "api/status") as r:
            st = (await r.json())["demo-hmc"]
        v = st.get("verdict") or {}
        print(f"\nverdict on the CNC: {verdict} (code {ctrl.verdict}); simulated machine time "
              f"{ctrl.machine_time_s / 60:.1f} min, run {st['run_id']}: {st['done']} touches")
        print(v.get("summary", st.get("reason", "")))
        for reason in v.get("reasons", []):
            print(f"  - {reason}")
        report = v.get("report")
        if report:
            analysis = json.loads(Path(report).with_suffix(".json").read_text())["analysis"]
            print(links_line(analysis["links"]))
            stab = analysis.get("stability")
            if stab:
                print(f"stability: pose {stab['worst']['pose']} probed again at the end, "
                      f"largest ball-centre shift {stab['max_shift_um']:.1f} µm between its "
                      f"two visits (health limit 8 µm)")
        print(f"report: {report}")
        if report and Path(report).with_suffix(".pdf").is_file():
            print(f"report for filing (PDF, A4): {Path(report).with_suffix('.pdf')}")
        print(f"demo wall time {time.monotonic() - t0:.1f} s")
        return 0 if verdict in ("PASS", "WARN", "FAIL") else 1
    finally:
        await stop_process(daemon)
        await sim.stop()


def links_line(links: dict[str, dict]) -> str:
    """The identified link errors of a report's JSON, each with its uncertainty and unit."""
    units = {"urad": "µrad", "um": "µm"}
    return "identified link errors (ISO 230-1, ± standard uncertainty): " + ", ".join(
        f"{k} {d['value']:+.1f} ± {d['std']:.1f} {units.get(d['unit'], d['unit'])}"
        for k, d in sorted(links.items()))


async def stop_process(proc: asyncio.subprocess.Process, grace_s: float = 20.0) -> None:
    """SIGTERM (the daemon finishes its journal and closes links), SIGKILL after ``grace_s``."""
    if proc.returncode is None:
        proc.terminate()
        try:
            await asyncio.wait_for(proc.wait(), grace_s)
        except TimeoutError:
            proc.kill()
            await proc.wait()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m demos.e2e", description=__doc__)
    ap.add_argument("--time-scale", type=float, default=0.02,
                    help="simulated machine time scale (1 = real time; default 0.02)")
    ap.add_argument("--out", type=Path,
                    help="folder for journal, reports and config (default: a new temp folder, "
                         "kept so the report can be opened)")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="rumba-demo-"))
    out.mkdir(parents=True, exist_ok=True)
    return asyncio.run(demo(args.time_scale, out.resolve()))


if __name__ == "__main__":
    sys.exit(main())
