"""LinuxCNC demo: LinuxCNC 2.9 headless (config/linuxcnc/, xyzbc-trt-kins, HAL probe carrying
our truth model) and the daemon (`rumba run`, a separate process) talking linuxcncrsh; the run is
started from the HMI's API, the verdict is written back to LinuxCNC (motion.analog-out-00).

``python -m demos.linuxcnc [--plan F] [--out DIR]`` (needs `bash .ci/install-peers.sh
linuxcnc`; ~1.5 min with the default 7-pose plan, ~5 min with thesis_annexB_14poses).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import secrets
import subprocess
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import aiohttp

from demos.e2e import _hmi, stop_process

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config"
MACHINE, ARTEFACT = "machines/linuxcnc_xyzbc.yaml", "artefacts/thesis_4ball.yaml"
ERRORS = "errors/linuxcnc_xyzbc.yaml"


def daemon_yaml(work: Path, port: int, plan: Path, *, writer: str = "demos/linuxcnc.py",
                name: str = "lcnc-trt", machine_file: Path = CONFIG / MACHINE,
                artefact: Path = CONFIG / ARTEFACT, hmi: str = "{enabled: false}") -> str:
    """The daemon.yaml of a LinuxCNC demo (one machine over linuxcncrsh on ``port``); ``hmi``
    the flow-style ``hmi:`` section, ``writer`` named in its first line."""
    return f"""# written by {writer}
store: {{path: {work / 'journal.sqlite'}}}
reports_dir: {work / 'reports'}
hmi: {hmi}
machines:
  - name: {name}
    machine: {machine_file}
    artefact: {artefact}
    plan: {plan}
    dialect: linuxcnc
    link: {{transport: linuxcnc, host: 127.0.0.1, port: {port}, prelude_mdi: [M429]}}
    touch_timeout_s: 60
    tolerances:
      default_rotation_urad: {{warn: 30, fail: 60}}
      default_translation_um: {{warn: 150, fail: 250}}
"""


def _analog_out(peer_dir: Path, n: int) -> float:
    fifo = (peer_dir / "fifo.path").read_text().strip()
    out = subprocess.run(["/usr/bin/halcmd", "getp", f"motion.analog-out-{n:02d}"],
                         env={**os.environ, "RTAPI_FIFO_PATH": f"{fifo}/rtapi_fifo"},
                         capture_output=True, text=True, timeout=20, check=True)
    return float(out.stdout)


def start_peer(work: Path) -> tuple[Any, Any]:
    """LinuxCNC headless in ``work/linuxcnc`` with the HAL probe carrying the demo truth
    (``ERRORS``): (the TruthModel, the running peer)."""
    from simulators import linuxcnc_peer
    from simulators.hal_probe import write_spec
    from simulators.truth import TruthModel

    truth = TruthModel.from_files(CONFIG / MACHINE, CONFIG / ARTEFACT, CONFIG / ERRORS)
    spec = work / "probe_spec.json"
    write_spec(truth, spec)
    return truth, linuxcnc_peer.up(spec, workdir=work / "linuxcnc")


async def demo(plan: Path, work: Path) -> int:
    from simulators import linuxcnc_peer

    t0 = time.monotonic()
    truth, peer = start_peer(work)
    print(f"LinuxCNC up (linuxcncrsh 127.0.0.1:{peer.port}, {time.monotonic() - t0:.1f} s); "
          f"HAL probe truth {ERRORS}")
    token = secrets.token_urlsafe(24)
    token_file = work / "hmi.token"
    token_file.write_text(token)
    token_file.chmod(0o600)
    cfg = work / "daemon.yaml"
    cfg.write_text(daemon_yaml(work, peer.port, plan,
                                hmi=f"{{host: 127.0.0.1, port: 0, token_file: {token_file}}}"))
    daemon = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "daemon.cli", "run", "--config", str(cfg), cwd=ROOT,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
    try:
        hmi = await _hmi(daemon.stdout, 60)
        async with aiohttp.ClientSession(
                headers={"Authorization": f"Bearer {token}"}) as http:
            async with http.post(hmi + "api/machines/lcnc-trt/start") as r:
                print(f"start from the HMI API: HTTP {r.status}")
            async with asyncio.timeout(1200):
                while True:
                    await asyncio.sleep(1.0)
                    async with http.get(hmi + "api/status") as r:
                        st = (await r.json())["lcnc-trt"]
                    # the report is written after the run's end: wait for it too
                    if not st["busy"] and (st.get("verdict") or {}).get(
                            "report_state") != "writing":
                        break
        v = st.get("verdict") or {}
        code = _analog_out(peer.dir, 0)
        print(f"\nrun {st['run_id']}: {st['state']} {st['reason']}; {st['done']} touches")
        print(f"verdict {v.get('status')} — written back to LinuxCNC: motion.analog-out-00 = "
              f"{code:g}")
        print(v.get("summary", ""))
        if v.get("report"):
            links = json.loads(Path(v["report"]).with_suffix(".json").read_text())
            links = links["analysis"]["links"]
            print("identified vs injected (µrad / µm): " + ", ".join(
                f"{k} {d['value']:+.1f}±{d['std']:.1f} ({truth.errors.links.get(k, 0):+g})"
                for k, d in sorted(links.items())))
            print(f"report: {v['report']}")
        print(f"demo wall time {time.monotonic() - t0:.1f} s")
        return 0 if v.get("status") in ("PASS", "WARN", "FAIL") else 1
    finally:
        await stop_process(daemon)
        linuxcnc_peer.down(peer.dir)


def run_demo(prog: str, prefix: str, demo: Callable[[Path, Path], Awaitable[int]],
             errors: tuple[type[BaseException], ...], argv: list[str] | None = None, *,
             description: str | None = None, raw_description: bool = False,
             default_plan: Path | None = None) -> int:
    """The command line of a LinuxCNC demo: ``--plan`` and ``--out`` (default: a new temp folder
    named ``prefix…``, kept), then ``demo(plan, out)``; an exception of ``errors`` (the peer
    missing, a demo step refused) ends as one line naming ``prog`` and exit code 2."""
    ap = argparse.ArgumentParser(prog=f"python -m {prog}", description=description,
                                 formatter_class=argparse.RawDescriptionHelpFormatter
                                 if raw_description else argparse.HelpFormatter)
    ap.add_argument("--plan", type=Path,
                    default=default_plan or CONFIG / "plans/linuxcnc_7poses.yaml")
    ap.add_argument("--out", type=Path, help="folder for journal, reports and config "
                                             "(default: a new temp folder, kept)")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix=prefix))
    out.mkdir(parents=True, exist_ok=True)
    try:
        return asyncio.run(demo(args.plan.resolve(), out.resolve()))
    except errors as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2


def main(argv: list[str] | None = None) -> int:
    from simulators.linuxcnc_peer import PeerError

    return run_demo("demos.linuxcnc", "rumba-demo-lcnc-", demo, (PeerError,), argv,
                    description=__doc__)


if __name__ == "__main__":
    sys.exit(main())
