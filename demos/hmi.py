"""`make demo-hmi`: the simulated CNC (OPC UA, Basic256Sha256 SignAndEncrypt + user/password),
the daemon (`rumba run`, its own process) and its HMI, with an account made for this session:
prints the URL and a one-time login (user ``demo``, engineer, a random password), then serves
until Ctrl-C, which stops the daemon (SIGTERM: it ends a run cleanly) and the simulator.

The demo machine FAILs its first check against the demo's shop limits (demos/limits.py); the
compensation panel proposes $TC_CARR changes within the machine file's guards (a proposal is
never a program); once the engineer confirms, the program that confirmation wrote is loaded
into the simulated SINUMERIK (what the operator does at the control; nothing the journal does
not show as confirmed is run) and the next check PASSes.

``python -m demos.hmi [--port P] [--out DIR] [--time-scale S]``
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import secrets
import shutil
import signal
import sys
import tempfile
from pathlib import Path

from demos.e2e import (
    ARTEFACT,
    CONFIG,
    DIALECT,
    ERRORS,
    MACHINE,
    PLAN,
    stop_process,
    tolerances_yaml,
)

USER = "demo"


def daemon_yaml(work: Path, url: str, pki: Path, server_cert: Path, port: int) -> str:
    return f"""# written by demos/hmi.py (make demo-hmi)
store: {{path: {work / 'journal.sqlite'}}}
reports_dir: {work / 'reports'}
hmi: {{host: 127.0.0.1, port: {port}, token_file: {work / 'hmi.token'}, users_file: users}}
machines:
  - name: demo-hmc
    machine: {CONFIG / MACHINE}
    artefact: {CONFIG / ARTEFACT}
    plan: {CONFIG / PLAN}
    dialect: {DIALECT}
    link:
      transport: opcua
      url: '{url}'
      security: Basic256Sha256_SignAndEncrypt
      certificate: {pki / 'client/cert.der'}
      private_key: {pki / 'client/key.pem'}
      server_certificate: {server_cert}
      user: {{name: rumba, password_env: RUMBA_DEMO_OPCUA_PASSWORD}}
    touch_timeout_s: 60
{tolerances_yaml()}"""


def write_secrets(work: Path) -> str:
    """The scripts' token and the demo account (engineer, random password); the password."""
    from daemon.hmi.users import User, hash_password, write_users

    token = work / "hmi.token"
    token.write_text(secrets.token_urlsafe(24))
    token.chmod(0o600)
    password = secrets.token_urlsafe(12)
    write_users(work / "users", {USER: User(USER, "engineer", hash_password(password))})
    return password


async def _banner(stdout: asyncio.StreamReader) -> str:
    """The daemon's startup lines until it says where the HMI listens ('' if it exited)."""
    while True:
        line = (await stdout.readline()).decode()
        if not line:
            return ""
        if line.startswith("rumba: HMI at "):
            return line.split("rumba: HMI at ", 1)[1].strip()


def unconfirmed(journal: Path, machine: str, program: Path) -> str:
    """Why the operator must not run ``program`` ("" when it may): it runs only a program a
    confirmation wrote — the journal's write that names it is the machine's current state
    (a compensation still applied, or the last rollback). A proposal is never a program, and
    any other file in the folder (an old proposal's, one copied there) is left alone."""
    from daemon.compensation import journal as cj
    from daemon.store.journal import Store

    store = Store(journal)
    try:
        written = cj.written(store, machine)
    finally:
        store.close()
    mine = [r for r in written if program.name in r.reason]
    if not mine:
        return "no confirmed compensation in the journal wrote it"
    row = mine[-1]
    if row.is_rollback:
        return "" if row is written[-1] else "a later write superseded this rollback"
    return "" if row.state == "applied" else f"compensation #{row.id} is {row.state}"


async def operator_pass(ctrl, reports: Path, journal: Path, machine: str,
                        seen: set[tuple[str, int]]) -> list[str]:
    """One look of the operator at the reports folder: each new program a confirmation wrote
    (compensation or rollback) is loaded and run on the simulated SINUMERIK once it is idle;
    anything else is named and left alone. What was done, one line each."""
    out = []
    for path in sorted(reports.glob("*.mpf")):
        key = (path.name, path.stat().st_mtime_ns)
        if key in seen:
            continue
        if ctrl.request or ctrl.state in ("running", "hold"):
            break  # a run is on the control: the operator waits for it to end
        seen.add(key)
        why = unconfirmed(journal, machine, path)
        if why:
            out.append(f"operator: not running {path.name}: {why}")
            continue
        await ctrl.load_program(path.read_text(encoding="utf-8"), DIALECT)
        await ctrl.start()
        state = await ctrl.wait_done(60)
        out.append(f"operator: ran {path.name} on the control ({state}); start the next "
                   "check to verify it")
    return out


async def load_compensations(ctrl, reports: Path, journal: Path, machine: str) -> None:
    """The operator at the control (``operator_pass`` every second); the programs already in
    the folder when the demo starts are not run again."""
    seen = {(p.name, p.stat().st_mtime_ns) for p in reports.glob("*.mpf")}
    while True:
        await asyncio.sleep(1.0)
        for line in await operator_pass(ctrl, reports, journal, machine, seen):
            print(line, flush=True)


async def serve(work: Path, port: int, time_scale: float) -> int:
    from contracts.opcua_certs import ensure_certificate
    from simulators.controller import VirtualController
    from simulators.frontends.opcua import OpcUaFrontend
    from simulators.truth import TruthModel

    pki = work / "pki"
    await ensure_certificate(pki / "client/cert.der", pki / "client/key.pem",
                             "urn:rumba-cnc:daemon", server=False)
    (pki / "trusted").mkdir(parents=True, exist_ok=True)
    shutil.copy(pki / "client/cert.der", pki / "trusted/daemon.der")
    opcua_password = secrets.token_urlsafe(16)
    truth = TruthModel.from_files(CONFIG / MACHINE, CONFIG / ARTEFACT, CONFIG / ERRORS)
    ctrl = VirtualController(truth, time_scale=time_scale, dialect=DIALECT)
    sim = OpcUaFrontend(ctrl, cert_dir=pki / "server", users={"rumba": opcua_password},
                        trusted_client_certs=[pki / "trusted"])
    url = await sim.start()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    daemon = None
    log = work / "daemon.log"
    try:
        cfg = work / "daemon.yaml"
        cfg.write_text(daemon_yaml(work, url, pki, sim.server_certificate, port))
        password = write_secrets(work)
        env = {**os.environ, "RUMBA_DEMO_OPCUA_PASSWORD": opcua_password}
        with log.open("ab") as err:  # the daemon's log (rotated by it) and its stderr
            daemon = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "daemon.cli", "run", "--config", str(cfg),
                "--log-file", str(log),
                cwd=Path(__file__).resolve().parents[1], env=env,
                stdout=asyncio.subprocess.PIPE, stderr=err,
                start_new_session=True)  # Ctrl-C reaches us; we stop the daemon in order
        assert daemon.stdout is not None
        (work / "daemon.pid").write_text(f"{daemon.pid}\n")
        banner = asyncio.ensure_future(_banner(daemon.stdout))
        waiter = asyncio.ensure_future(stop.wait())
        await asyncio.wait({banner, waiter}, return_when=asyncio.FIRST_COMPLETED)
        waiter.cancel()
        if not banner.done():
            banner.cancel()
            print("stopped before the daemon was up")
            return 130
        hmi = banner.result()
        if not hmi:
            tail = log.read_text(errors="replace").strip().splitlines()[-5:]
            print("error: the daemon exited during startup:\n  " + "\n  ".join(tail),
                  file=sys.stderr)
            return 1
        print(f"simulated CNC (OPC UA, SignAndEncrypt) at {url}; machine errors {ERRORS}")
        print(f"HMI:      {hmi}")
        print(f"login:    user {USER}  password {password}   (engineer; made for this session)")
        print(f"files:    {work} (journal, reports, daemon.log); more accounts: "
              f"rumba users --file {work / 'users'} add NAME --role operator")
        print("Ctrl-C stops the daemon and the simulated CNC", flush=True)
        operator = asyncio.ensure_future(load_compensations(
            ctrl, work / "reports", work / "journal.sqlite", "demo-hmc"))
        await stop.wait()
        operator.cancel()
        print("\nstopping …", flush=True)
        return 0
    finally:
        if daemon is not None:
            await stop_process(daemon)
        with contextlib.suppress(Exception):
            await sim.stop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        print("stopped: daemon and simulated CNC", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m demos.hmi", description=__doc__)
    ap.add_argument("--port", type=int, default=8470, help="HMI port (0: any free port)")
    ap.add_argument("--time-scale", type=float, default=0.05,
                    help="simulated machine time scale (1 = real time; default 0.05)")
    ap.add_argument("--out", type=Path, help="folder for journal, reports and config "
                                             "(default: a new temp folder, kept)")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="rumba-demo-hmi-"))
    out.mkdir(parents=True, exist_ok=True)
    return asyncio.run(serve(out.resolve(), args.port, args.time_scale))


if __name__ == "__main__":
    sys.exit(main())
