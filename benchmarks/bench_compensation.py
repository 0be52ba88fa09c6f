"""Time of the compensation view: `rumba compensate RUN` and GET /api/compensation."""

# .venv/bin/python -m benchmarks.bench_compensation [--runs 5]   (also in `make bench`)
#
# One verification run of the thesis machine (Siemens controller_kinematics section, Table B.2
# link errors, ``--plan`` of config/plans) made by the simulated CNC over OPC UA through the
# real daemon (the world of tests/test_hmi_compensate.py), then: the HMI view computed by a
# fresh view cache (what a page's first GET after a daemon restart costs), GET
# /api/compensation over HTTP (served from the cache), ``propose()`` in process, ``rumba
# compensate RUN`` in process (the command's own work) and from the shell (a fresh process
# each time, interpreter start-up and imports included). Median and best of ``--runs``.

from __future__ import annotations

import argparse
import asyncio
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.bench_cli import ROOT, rumba


def _fmt(name: str, times: list[float]) -> str:
    return (f"{name:<46} median {statistics.median(times) * 1e3:8.1f} ms   best "
            f"{min(times) * 1e3:8.1f} ms   (n={len(times)})")


async def _daemon_side(tmp: Path, runs: int, plan: str) -> tuple[str, list[str]]:
    import aiohttp

    from benchmarks.rigs.hmi_compensation import bearer, run_once, world
    from daemon.compensation.propose import propose
    from daemon.hmi.compensation_api import Views
    from daemon.store.journal import Store

    lines = [f"plan {plan}"]
    async with world(tmp, plan=plan) as svc, aiohttp.ClientSession() as http:
        run_id = await run_once(svc)
        session = svc.sessions["mill1"]
        cold = []
        for _ in range(runs):
            views = Views(svc.store.path)
            t0 = time.perf_counter()
            out, _ = await asyncio.to_thread(views.get, session)
            cold.append(time.perf_counter() - t0)
            await asyncio.to_thread(views.close)
            assert out["run"]["id"] == run_id and out["proposal"], out
        lines.append(_fmt("HMI view, fresh cache (first GET)", cold))
        warm = []
        for _ in range(runs * 4):
            t0 = time.perf_counter()
            r = await http.get(svc.hmi_url + "api/compensation?machine=mill1",
                               headers=bearer())
            assert r.status == 200
            await r.read()
            warm.append(time.perf_counter() - t0)
        lines.append(_fmt("GET /api/compensation over HTTP", warm))
        store = Store(svc.store.path)
        try:
            inproc = []
            for _ in range(runs):
                t0 = time.perf_counter()
                propose(session.setup, store, run_id)
                inproc.append(time.perf_counter() - t0)
            lines.append(_fmt("propose() in process", inproc))
        finally:
            store.close()
    return run_id, lines


def _in_process(argv: list[str], runs: int) -> list[float]:
    """The command's own work: ``daemon.cli.main.main`` called again in this process (its
    imports done by the first, untimed call), output discarded."""
    import contextlib
    import io

    from daemon.cli.main import main as cli

    times = []
    for k in range(runs + 1):
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            assert cli(argv) == 0
        if k:
            times.append(time.perf_counter() - t0)
    return times


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="bench_compensation")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--plan", default="thesis_annexB_14poses", help="a plan of config/plans")
    args = ap.parse_args(argv if argv is not None else [])
    with tempfile.TemporaryDirectory(prefix="rumba-bench-comp-") as d:
        tmp = Path(d)
        run_id, lines = asyncio.run(_daemon_side(tmp, args.runs, args.plan))
        cmd = [*rumba(), "compensate", "--config", str(tmp / "daemon.yaml"), run_id]
        lines.append(_fmt("rumba compensate RUN in process (imports done)",
                          _in_process(cmd[-4:], args.runs)))
        shell = []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
            shell.append(time.perf_counter() - t0)
            assert p.returncode == 0, p.stdout + p.stderr
        lines.append(_fmt("rumba compensate RUN (fresh process)", shell))
    print("\n".join(lines))


if __name__ == "__main__":
    main(sys.argv[1:])
