"""Fleet demo: a real PostgreSQL and mosquitto on loopback, three simulated machines (Fanuc over
OPC UA, Siemens over Modbus TCP, Heidenhain over a serial DNC line) with three daemons
(``rumba run``, separate processes) sharing the fleet store and the broker; all three CNCs
raise their start-of-shift request at once; the fleet table and the fleet page's URL are
printed, and the page is served until Ctrl-C.

``python -m demos.fleet [--time-scale S] [--out DIR] [--exit]``; needs
``bash .ci/install-peers.sh postgresql mosquitto`` (``make demo-fleet`` runs it).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import secrets
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from contracts.jobs import VERDICT_CODES
from demos.e2e import CONFIG, ERRORS, MACHINE, PLAN, ROOT, stop_process
from demos.limits import tolerances

ARTEFACT = "artefacts/thesis_4ball.yaml"
BAUD = 115_200  # a common DNC rate
SITE = "demo"
VERDICT_NAMES = {code: name for name, code in VERDICT_CODES.items()}
# (machine name, dialect, transport): three controls, three ways to reach them
MACHINES = (("hmc-fanuc", "fanuc", "opcua"), ("mill-siemens", "siemens", "modbus"),
            ("mill-heidenhain", "heidenhain", "serial"))


async def start_cnc(dialect: str, transport: str, time_scale: float) -> tuple[Any, dict, Any]:
    """A simulated control behind its real front-end: (controller, link section, stop)."""
    from simulators.controller import VirtualController
    from simulators.truth import TruthModel

    truth = TruthModel.from_files(CONFIG / MACHINE, CONFIG / ARTEFACT, CONFIG / ERRORS)
    ctrl = VirtualController(truth, time_scale=time_scale, dialect=dialect)
    if transport == "opcua":
        from simulators.frontends.opcua import OpcUaFrontend

        fe = OpcUaFrontend(ctrl, security="none")  # loopback demo; real controls: SignAndEncrypt
        return ctrl, {"transport": "opcua", "url": await fe.start(), "security": "none"}, fe.stop
    if transport == "modbus":
        from simulators.frontends.modbus import ModbusFrontend

        fe = ModbusFrontend(ctrl)
        port = await fe.start("127.0.0.1", 0)
        return ctrl, {"transport": "modbus", "host": "127.0.0.1", "port": port}, fe.stop
    from simulators.frontends.serial import SerialFrontend, SerialSettings

    # A 4 KiB receive buffer (the simulator's default is a pessimistic 256 B): the simulated
    # control shares this process with two others, and its receive side is only as timely as
    # this event loop; with 256 B a loaded 2-core machine raised false overflow alarms.
    fe = SerialFrontend(ctrl, SerialSettings(baudrate=BAUD, framing="7E1", rx_buffer_bytes=4096))
    url = await fe.open_pty()  # a real tty device, as a DNC line on a USB adapter
    return ctrl, {"transport": "serial", "url": url, "baudrate": BAUD, "framing": "7E1",
                  "request_machine": ctrl.machine_id, "tx_chunk_bytes": 64}, fe.close


def daemon_yaml(work: Path, name: str, dialect: str, link: dict, dsn: str, mqtt_port: int,
                token_file: Path) -> Path:
    doc = {
        "store": {"path": str(work / "journal.sqlite"), "url": dsn},
        "reports_dir": str(work / "reports"),
        "hmi": {"host": "127.0.0.1", "port": 0, "token_file": str(token_file)},
        "mqtt": {"host": "127.0.0.1", "port": mqtt_port, "site": SITE},
        "machines": [{
            "name": name, "machine": str(CONFIG / MACHINE), "artefact": str(CONFIG / ARTEFACT),
            "plan": str(CONFIG / PLAN), "dialect": dialect, "link": link,
            "touch_timeout_s": 60,
            "tolerances": tolerances()}]}  # the demo's shop limits, with their basis
    work.mkdir(parents=True, exist_ok=True)
    path = work / "daemon.yaml"
    path.write_text("# written by demos/fleet.py\n" + yaml.safe_dump(doc, sort_keys=False))
    return path


async def banner(proc: asyncio.subprocess.Process, name: str) -> str:
    """Read a daemon's output until it says where its HMI listens (or it exits: then why);
    then keep draining it. No clock: a loaded computer starts a daemon slowly."""
    assert proc.stdout is not None
    while True:
        line = (await proc.stdout.readline()).decode()
        if not line:
            raise DemoFailed(f"the daemon of {name} exited during startup (code "
                             f"{await proc.wait()}; see its daemon.log)")
        if line.startswith("rumba: HMI at "):
            break
    asyncio.get_running_loop().create_task(_drain(proc.stdout))
    return line.split("rumba: HMI at ", 1)[1].strip()


async def _drain(stream: asyncio.StreamReader) -> None:
    while await stream.readline():
        pass


async def mqtt_count(port: int, counts: dict[str, int]) -> None:
    import aiomqtt

    async with aiomqtt.Client("127.0.0.1", port) as client:
        await client.subscribe(f"rumba/{SITE}/#")
        async for msg in client.messages:
            leaf = str(msg.topic).rsplit("/", 1)[-1]
            counts[leaf] = counts.get(leaf, 0) + 1


STALL_S = 180.0
"""No progress at all (no touch on any CNC, no state change in the store) for this long: the
demo gives up, naming where each machine stood. A busy machine only makes runs slower."""


class DemoStalled(Exception):
    """The fleet made no progress for ``STALL_S``; the message says where it stood."""


class DemoFailed(Exception):
    """A machine's run ended without a verdict, or its daemon exited; the message says why."""


ENDED = ("DONE", "FAILED", "ABORTED", "INTERRUPTED")


async def runs_ended(hmis: dict[str, str], token: str,
                     procs: dict[str, asyncio.subprocess.Process] | None = None,
                     stall_s: float = STALL_S, before: dict[str, str | None] | None = None
                     ) -> dict[str, dict]:
    """Wait on each daemon's own state of its run (its HMI's /api/status, bearer token) until
    every machine's run has ended; the statuses. A run that ends FAILED, ABORTED or
    INTERRUPTED, or a daemon that exits, fails at once with the reason (``DemoFailed``); a
    slow run is waited for as long as its touches or states move (``DemoStalled`` only after
    ``stall_s`` without any change): a busy computer is slow, not stuck. ``before``: each
    machine's run id before the starts (default none: fresh journals)."""
    import aiohttp

    started: dict[str, str] = {}
    last, moved = None, time.monotonic()
    async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {token}"}) as http:
        while True:
            for name, p in (procs or {}).items():
                if p.returncode is not None:
                    raise DemoFailed(f"{name}: the daemon exited (code {p.returncode}); see "
                                     "its daemon.log")
            now: dict[str, dict] = {}
            for name, url in hmis.items():
                async with http.get(url + "api/status") as r:
                    now[name] = (await r.json())[name]
            for name, st in now.items():
                if st["run_id"] and st["run_id"] != (before or {}).get(name):
                    started[name] = st["run_id"]
                if name in started and not st["busy"] and st["state"] in ENDED[1:]:
                    raise DemoFailed(f"{name}: run {started[name]} {st['state']}: "
                                     f"{st['reason']}")
            if len(started) == len(hmis) and all(not s["busy"] for s in now.values()):
                return now
            key = [(n, s["run_id"], s["state"], s["done"]) for n, s in sorted(now.items())]
            if key != last:
                last, moved = key, time.monotonic()
            elif time.monotonic() - moved > stall_s:
                where = ", ".join(f"{n} {s['state']} {s['done']}/{s['total']} touches"
                                  for n, s in sorted(now.items()))
                raise DemoStalled(f"no progress for {stall_s:g} s (no touch, no state change):"
                                  f" {where}; see the daemon.log files")
            await asyncio.sleep(0.2)


async def fleet_in_store(dsn: str, names: list[str], progress: Callable[[], object],
                         stall_s: float = STALL_S) -> list[dict]:
    """Poll the fleet store until every machine's run has ended there: a verdict with its
    report, or an error end (a failed run is shown, never waited for forever). Waits as long
    as something moves (``progress()``: e.g. the CNCs' touch counts, plus the store's states),
    not a fixed wall-clock budget: a loaded computer is slow, not stuck."""
    from daemon.store.pg import PgStore

    store = await PgStore.connect(dsn, migrate=False)
    try:
        last, moved = None, time.monotonic()
        while True:
            fleet = await store.fleet()
            if sum(1 for m in fleet if m["machine"] in names and m["run_id"] and (
                    m["has_report"] or m["state"] != "DONE")) == len(names):
                return fleet
            now = (progress(), [(m["machine"], m["run_id"], m["state"]) for m in fleet])
            if now != last:
                last, moved = now, time.monotonic()
            elif time.monotonic() - moved > stall_s:
                where = ", ".join(f"{m['machine']} {m['state'] or 'no run'}" for m in fleet
                                  if m["machine"] in names) or "no run in the fleet store"
                raise DemoStalled(f"no progress for {stall_s:g} s (no touch on any CNC, no "
                                  f"state change): {where}; see the daemon.log files")
            await asyncio.sleep(0.2)
    finally:
        await store.close()


def print_table(fleet: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    from daemon.fleet.view import age_text, when

    t = Table(title="rumba fleet")
    for col in ("machine", "dialect / transport", "verdict", "date", "age", "run", "summary"):
        t.add_column(col)
    style = {"PASS": "green", "WARN": "yellow", "FAIL": "red", "ERROR": "magenta"}
    now = time.time()
    for m in fleet:
        end = m["ended_at"] or m["started_at"]
        t.add_row(m["machine"], f"{m['dialect']} / {m['transport']}",
                  f"[{style.get(m['verdict'], '')}]{m['verdict']}[/]", when(end),
                  age_text(None if end is None else now - end), m["run_id"] or "—",
                  (m["summary"] or "")[:60])
    Console(width=None if sys.stdout.isatty() else 150).print(t)


async def demo(time_scale: float, out: Path, stay: bool) -> int:
    from aiohttp import web

    from daemon.analysis.pipeline import prepare
    from daemon.config import load_daemon_config
    from daemon.fleet.app import create_fleet_app
    from simulators.fleet_peers import MosquittoPeer, PeerUnavailable, PostgresPeer, free_port

    t0 = time.monotonic()
    try:
        pg = await asyncio.to_thread(PostgresPeer)
    except PeerUnavailable as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    stack = contextlib.AsyncExitStack()
    stack.callback(pg.close)
    procs: list[asyncio.subprocess.Process] = []
    try:
        mqtt = MosquittoPeer()
        stack.callback(mqtt.close)
        print(f"PostgreSQL at {pg.dsn}, mosquitto at 127.0.0.1:{mqtt.port}")
        token = secrets.token_urlsafe(24)
        token_file = out / "fleet.token"
        token_file.write_text(token)
        token_file.chmod(0o600)
        counts: dict[str, int] = {}
        sub = asyncio.get_running_loop().create_task(mqtt_count(mqtt.port, counts))

        async def end_sub() -> None:
            sub.cancel()
            with contextlib.suppress(BaseException):
                await sub

        stack.push_async_callback(end_sub)
        ctrls, hmis = {}, {}
        for name, dialect, transport in MACHINES:
            ctrl, link, stop = await start_cnc(dialect, transport, time_scale)
            stack.push_async_callback(stop)
            cfg = daemon_yaml(out / name, name, dialect, link, pg.dsn, mqtt.port, token_file)
            if transport != "opcua":  # what an operator copies to the control once (FN 16
                setup = load_daemon_config(cfg).machines[name]  # format files: no file
                ctrl.files.update(prepare(setup, "setup").job.files)  # transfer on DNC/Modbus)
            ctrls[name] = ctrl
            # The daemon's log, rotated by the daemon; its stderr (a start-up error) appended
            log_file = out / name / "daemon.log"
            with log_file.open("ab") as log:
                proc = await asyncio.create_subprocess_exec(
                    sys.executable, "-m", "daemon.cli", "run", "--config", str(cfg),
                    "--log-file", str(log_file), cwd=ROOT, stdout=asyncio.subprocess.PIPE,
                    stderr=log)
            procs.append(proc)
            hmis[name] = await banner(proc, name)
            print(f"  {name}: {dialect} over {transport}; HMI at {hmis[name]}")
        print(f"daemons up ({time.monotonic() - t0:.1f} s); the three CNCs raise their "
              "start-of-shift request at once")
        t1 = time.monotonic()
        for ctrl in ctrls.values():
            ctrl.raise_start_request()
        # each daemon's own run state first (a failed run ends the demo at once, naming why),
        # then the fleet store the journals drain to
        await runs_ended(hmis, token, dict(zip(ctrls, procs, strict=True)))
        fleet = await fleet_in_store(pg.dsn, list(ctrls), lambda: [
            (len(c.touches), c.state) for c in ctrls.values()])
        for name, c in ctrls.items():
            cnc = VERDICT_NAMES.get(int(c.verdict), c.verdict) if c.verdict else "none"
            print(f"  {name}: verdict on the CNC {cnc}")
        print(f"three checks done and in the fleet store in {time.monotonic() - t1:.1f} s; "
              f"MQTT messages seen: {json.dumps(dict(sorted(counts.items())))}")
        print_table(fleet)
        app = create_fleet_app(pg.dsn, token, reports_dirs=[out / n / "reports" for n in ctrls],
                               bind_host="127.0.0.1")
        runner = web.AppRunner(app, handle_signals=False)
        await runner.setup()
        stack.push_async_callback(runner.cleanup)
        port = free_port()
        await web.TCPSite(runner, "127.0.0.1", port).start()
        print(f"fleet page: http://127.0.0.1:{port}/  (token in {token_file})")
        print(f"demo wall time {time.monotonic() - t0:.1f} s; files in {out}")
        if stay:
            print("serving until Ctrl-C …", flush=True)
            stop = asyncio.Event()
            for sig in (signal.SIGINT, signal.SIGTERM):
                asyncio.get_running_loop().add_signal_handler(sig, stop.set)
            await stop.wait()
        return 0 if all(m["verdict"] in ("PASS", "WARN", "FAIL") for m in fleet
                        if m["machine"] in ctrls) else 1
    finally:
        await asyncio.gather(*(stop_process(p) for p in procs))
        await stack.aclose()
        print("stopped: daemons, simulated CNCs, fleet page, mosquitto, PostgreSQL")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m demos.fleet", description=__doc__)
    ap.add_argument("--time-scale", type=float, default=0.02,
                    help="simulated machine time scale (1 = real time; default 0.02)")
    ap.add_argument("--out", type=Path, help="folder for journals, reports and configs "
                                             "(default: a new temp folder, kept)")
    ap.add_argument("--exit", action="store_true",
                    help="exit after printing the table instead of serving the page")
    args = ap.parse_args(argv)
    out = (args.out or Path(tempfile.mkdtemp(prefix="rumba-fleet-demo-"))).resolve()
    out.mkdir(parents=True, exist_ok=True)
    try:
        return asyncio.run(demo(args.time_scale, out, not args.exit))
    except (DemoStalled, DemoFailed) as e:
        print(f"demo-fleet: {e} (in {out})", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
