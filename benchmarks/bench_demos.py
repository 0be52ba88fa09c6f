"""The demos end to end from the shell: ``make demo`` (python -m demos.e2e) and ``make
demo-fleet`` (python -m demos.fleet --exit), wall and CPU time of each run."""

# .venv/bin/python -m benchmarks.bench_demos [--runs 1] [--only e2e|fleet]
#
# Wall: from the command to its exit (every process it started stopped). CPU: user + system of
# the demo and the processes it reaped (daemons, simulated controls, mosquitto), from rusage;
# PostgreSQL's server is not in it (pg_ctl detaches it). The fleet demo needs PostgreSQL and
# mosquitto (bash .ci/install-peers.sh postgresql mosquitto). Targets at load ≤ 4 on 2 cores:
# make demo ≤ 30 s, make demo-fleet ≤ 120 s wall. Each demo keeps its output folder in the
# temp dir (the reports a user opens); this benchmark removes it after the run.

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEMOS = {"e2e": ["-m", "demos.e2e", "--profile", "gateway"],
         "fleet": ["-m", "demos.fleet", "--exit"]}
LABELS = {"e2e": "make demo (OPC UA SignAndEncrypt, 300 touches, compensation, re-check)",
          "fleet": "make demo-fleet --exit (3 controls × 300 touches, 3 daemons, PostgreSQL, "
                   "MQTT)"}


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_once(name: str) -> tuple[float, float]:
    """(wall s, CPU s) of one run of demo ``name``; exits with its output if it fails."""
    c, t = _cpu_s(), time.perf_counter()
    proc = subprocess.run([sys.executable, *DEMOS[name]], cwd=ROOT, capture_output=True,
                          text=True)
    wall, cpu = time.perf_counter() - t, _cpu_s() - c
    out = proc.stdout + proc.stderr
    for folder in re.findall(r"(/\S*rumba-(?:fleet-)?demo-[A-Za-z0-9_]+)", out):
        if Path(folder).is_dir() and Path(folder).parent == Path(tempfile.gettempdir()):
            shutil.rmtree(folder, ignore_errors=True)
    if proc.returncode != 0:
        raise SystemExit(f"{name}: exit {proc.returncode}\n{out[-3000:]}")
    return wall, cpu


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1, help="runs of each demo (default 1)")
    ap.add_argument("--only", choices=sorted(DEMOS), help="one demo only")
    args = ap.parse_args([] if argv is None else argv)
    for name in [args.only] if args.only else list(DEMOS):
        load = os.getloadavg()[0]
        runs = [run_once(name) for _ in range(args.runs)]
        wall, cpu = [r[0] for r in runs], [r[1] for r in runs]
        print(f"{LABELS[name]}: wall median {statistics.median(wall):.1f} s (best "
              f"{min(wall):.1f}), CPU median {statistics.median(cpu):.1f} s over {len(runs)} "
              f"run(s), load {load:.1f} at the start")


if __name__ == "__main__":
    main(sys.argv[1:])
