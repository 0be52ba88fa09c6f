"""End-to-end demo: the simulated CNC (OPC UA, Basic256Sha256 SignAndEncrypt + user/password)
and the daemon (`rumba run`, a separate process) on free loopback ports; the CNC raises its
start-of-shift request, the daemon runs the thesis annex-B plan, and the verdict comes back.

The story a shop lives: the demo machine (a light collision moved its C axis line
38 µm) FAILs against limits derived from its parts' tolerance (demos/limits.py); the proposed
compensation is within the machine file's guards, an engineer confirms it (`rumba compensate
--confirm --by`), the reviewed $TC_CARR program is loaded into the control, and the
verification run PASSes.

``--profile sinumerik``: the same story on the control's own OPC UA server as Siemens ships it
(the SINUMERIK profile: the program written into "Part Programs" and selected, the machine's PLC
presses NC start on the start request, results from the program's R parameters), the reviewed
compensation program sent into "Part Programs" for the operator to select and start. The default
``--profile gateway`` is rumba's own address space (a PLC or an edge box implements it).

``python -m demos.e2e [--profile gateway|sinumerik] [--time-scale S] [--out DIR]`` prints the
verdict and report path.
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
import yaml

from contracts.jobs import VERDICT_CODES
from demos.limits import tolerances
from demos.progress import RunProgress, watch

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config"
VERDICT_NAMES = {code: name for name, code in VERDICT_CODES.items()}
MACHINE, ARTEFACT = "machines/thesis_wcbxfzyt.yaml", "artefacts/thesis_4ball.yaml"
PLAN, ERRORS = "plans/shift_start_14poses.yaml", "errors/demo_hmc.yaml"
# The machine file's controller_kinematics is a SINUMERIK 840D swivel table ($TC_CARR): the
# demo machine is configured as that control, so compensation proposes its own addresses.
DIALECT = "siemens"


def tolerances_yaml(indent: int = 4) -> str:
    """The demo's shop limits (demos/limits.py) as a daemon.yaml ``tolerances`` section."""
    text = yaml.safe_dump({"tolerances": tolerances()}, sort_keys=False, allow_unicode=True,
                          width=90)
    return "".join(" " * indent + line for line in text.splitlines(keepends=True))


def _daemon_yaml(work: Path, url: str, pki: Path, server_cert: Path, token_file: Path,
                 profile: str = "gateway") -> str:
    transport = "sinumerik" if profile == "sinumerik" else "opcua  # the gateway profile"
    return f"""# written by demos/e2e.py
store: {{path: {work / 'journal.sqlite'}}}
reports_dir: {work / 'reports'}
hmi: {{host: 127.0.0.1, port: 0, token_file: {token_file}}}
machines:
  - name: demo-hmc
    machine: {CONFIG / MACHINE}
    artefact: {CONFIG / ARTEFACT}
    plan: {CONFIG / PLAN}
    dialect: {DIALECT}
    link:
      transport: {transport}
      url: '{url}'
      security: Basic256Sha256_SignAndEncrypt
      certificate: {pki / 'client/cert.der'}
      private_key: {pki / 'client/key.pem'}
      server_certificate: {server_cert}
      user: {{name: rumba, password_env: RUMBA_DEMO_OPCUA_PASSWORD}}
    touch_timeout_s: 60
{tolerances_yaml()}"""



async def settled_status(hmi: str, token: str, machine: str) -> dict:
    """The machine's HMI status once its last run's report is written or failed (
    the verdict reaches the CNC first, the report is rendered after the run's end)."""
    async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {token}"}) as http:
        while True:
            async with http.get(hmi + "api/status") as r:
                st = (await r.json())[machine]
            if (st.get("verdict") or {}).get("report_state") != "writing":
                return st
            await asyncio.sleep(0.2)

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


async def demo(time_scale: float, work: Path, profile: str = "gateway") -> int:
    from contracts.opcua_certs import ensure_certificate
    from simulators.controller import VirtualController
    from simulators.frontends.opcua import OpcUaFrontend
    from simulators.frontends.sinumerik import SinumerikFrontend
    from simulators.truth import TruthModel

    t0 = time.monotonic()
    pki = work / "pki"
    await ensure_certificate(pki / "client/cert.der", pki / "client/key.pem",
                             "urn:rumba-cnc:daemon", server=False)
    (pki / "trusted").mkdir(parents=True, exist_ok=True)
    shutil.copy(pki / "client/cert.der", pki / "trusted/daemon.der")
    password = secrets.token_urlsafe(16)
    truth = TruthModel.from_files(CONFIG / MACHINE, CONFIG / ARTEFACT, CONFIG / ERRORS)
    ctrl = VirtualController(truth, time_scale=time_scale, dialect=DIALECT)
    front = SinumerikFrontend if profile == "sinumerik" else OpcUaFrontend
    sim = front(ctrl, cert_dir=pki / "server", users={"rumba": password},
                trusted_client_certs=[pki / "trusted"])
    url = await sim.start()
    what = ("SINUMERIK OPC UA server: file system, Select, R parameters; its PLC presses NC "
            "start on the start request" if profile == "sinumerik" else
            "rumba gateway address space")
    print(f"simulated CNC (OPC UA, SignAndEncrypt, {what}) at {url}; errors {ERRORS}")
    token_file = work / "hmi.token"
    token = secrets.token_urlsafe(24)
    token_file.write_text(token)
    token_file.chmod(0o600)
    cfg = work / "daemon.yaml"
    cfg.write_text(_daemon_yaml(work, url, pki, sim.server_certificate, token_file, profile))
    env = {**os.environ, "RUMBA_DEMO_OPCUA_PASSWORD": password}
    daemon = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "daemon.cli", "run", "--config", str(cfg), cwd=ROOT, env=env,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
    watcher = None
    try:
        hmi = await _hmi(daemon.stdout, 60)
        print(f"daemon up ({time.monotonic() - t0:.1f} s); the CNC raises its start-of-shift "
              "request")
        watcher = asyncio.create_task(watch({"demo-hmc": hmi}, token, RunProgress(t0)))
        ctrl.raise_start_request()
        async with asyncio.timeout(240):
            while not (ctrl.done and ctrl.verdict):
                await asyncio.sleep(0.1)
        verdict = VERDICT_NAMES.get(int(ctrl.verdict), str(ctrl.verdict))
        st = await settled_status(hmi, token, "demo-hmc")
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
        if verdict == "FAIL" and not await compensate_and_verify(cfg, env, ctrl, st["run_id"],
                                                                 hmi, token, sim):
            return 1
        print(f"demo wall time {time.monotonic() - t0:.1f} s")
        return 0 if verdict in ("PASS", "WARN", "FAIL") else 1
    finally:
        if watcher is not None:
            watcher.cancel()
        await stop_process(daemon)
        await sim.stop()


async def _rumba(env: dict[str, str], *args: str) -> tuple[int, str]:
    """A ``rumba`` command in its own process: (exit code, its output)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "daemon.cli", *args, cwd=ROOT, env=env,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT)
    out, _ = await proc.communicate()
    return int(proc.returncode or 0), out.decode()


async def compensate_and_verify(cfg: Path, env: dict[str, str], ctrl, run_id: str, hmi: str,
                                token: str, sim=None) -> bool:
    """The FAIL's follow-up: the proposal, an engineer's confirmation, the reviewed program
    loaded into the control (as an operator does on a SINUMERIK), the verification run."""
    print(f"\nFAIL: an engineer reviews the compensation proposal and confirms it (rumba "
          f"compensate {run_id} --confirm --by 'demo engineer'; within the machine file's "
          "guards)")
    code, out = await _rumba(env, "compensate", "--config", str(cfg), run_id, "--confirm",
                             "--by", "demo engineer")
    print("  " + out.strip().replace("\n", "\n  "))
    program = next((ln.split("program: ", 1)[1].strip() for ln in out.splitlines()
                    if ln.startswith("program: ")), "")
    if code != 0 or not program:
        return False
    if hasattr(sim, "operator_select"):  # the SINUMERIK profile sent it into Part Programs
        from drivers.sinumerik.transfer import COMPENSATION_PROGRAM

        print(f"  the operator selects {COMPENSATION_PROGRAM}.MPF (sent by rumba) and presses "
              "NC start")
        await sim.operator_select(COMPENSATION_PROGRAM)
        await sim.nc_start()
        name = f"{COMPENSATION_PROGRAM}.MPF"
    else:  # the gateway profile: the operator loads the file from the reports folder
        await ctrl.load_program(Path(program).read_text(encoding="utf-8"), DIALECT)
        await ctrl.start()
        name = Path(program).name
    if await ctrl.wait_done(60) != "done":
        print(f"error: the control refused the compensation program: {ctrl.alarm}")
        return False
    print(f"  the control ran {name}: its $TC_CARR values now hold the change")
    print("verification run: the CNC raises its start request again")
    ctrl.raise_start_request()
    while not (ctrl.done and ctrl.verdict):
        await asyncio.sleep(0.1)
    st = await settled_status(hmi, token, "demo-hmc")
    verdict = VERDICT_NAMES.get(int(ctrl.verdict), str(ctrl.verdict))
    v = st.get("verdict") or {}
    print(f"verification verdict: {verdict}, run {st['run_id']}: {v.get('summary', '')}")
    if v.get("report"):
        analysis = json.loads(Path(v["report"]).with_suffix(".json").read_text())["analysis"]
        print(links_line(analysis["links"]))
        print(f"report: {v['report']}")
    return verdict in ("PASS", "WARN", "FAIL")


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
    ap.add_argument("--profile", choices=("gateway", "sinumerik"), default="gateway",
                    help="the control's OPC UA as rumba's gateway address space (default) or as "
                         "a SINUMERIK's own server")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="rumba-demo-"))
    out.mkdir(parents=True, exist_ok=True)
    return asyncio.run(demo(args.time_scale, out.resolve(), args.profile))


if __name__ == "__main__":
    sys.exit(main())
