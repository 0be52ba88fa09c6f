"""Daemon benchmarks: journal commit latency (FULL vs NORMAL), the daemon's own work per touch,
its overhead per touch on each transport against simulated machine time (target ≤ 20 ms),
resident memory during a 175-pose run, and the end-to-end demo wall time.

``python -m benchmarks bench_daemon`` (figures printed; nothing asserted).
"""

from __future__ import annotations

import asyncio
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config"


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def bench_journal(n: int = 400) -> None:
    from contracts.messages import ProbeHit
    from daemon.store.journal import Store

    for sync in ("FULL", "NORMAL"):
        with tempfile.TemporaryDirectory(dir=ROOT) as tmp:  # the project's disk, not tmpfs
            s = Store(Path(tmp) / "j.sqlite", synchronous=sync)  # type: ignore[arg-type]
            s.new_run("B", "m", "bench")
            lat = []
            for k in range(1, n + 1):
                hit = ProbeHit(seq=k, pose=k // 20, ball="B1", touch=1 + k % 5,
                               axes={"X": 1.0, "Y": 2.0, "Z": 3.0, "B": 0.0, "C": 0.0},
                               triggered=True, raw="RUMBA 1 0 0 B1 1 1 1.0 2.0 3.0 0.0 0.0")
                t = time.perf_counter()
                s.journal_hit("B", hit)
                lat.append((time.perf_counter() - t) * 1e3)
            s.close()
        lat.sort()
        print(f"journal commit per hit, synchronous={sync}: median {statistics.median(lat):.2f} "
              f"ms, p99 {lat[int(0.99 * n)]:.2f} ms, max {lat[-1]:.2f} ms ({n} hits)")


async def bench_session_175() -> None:
    """The daemon's own cost per touch (journal + bookkeeping + progress), without transport,
    on a 175-pose × 4-ball run (3 500 touches), plus identification/report time and memory."""
    from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
    from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
    from daemon.run.session import Session
    from daemon.store.journal import Store

    setup = thesis_setup(plan="thesis_ch4_175poses")
    rows = thesis_rows(setup)
    rss0 = _rss_mb()
    peak = [rss0]

    async def sample() -> None:
        while True:
            peak[0] = max(peak[0], _rss_mb())
            await asyncio.sleep(0.02)

    with tempfile.TemporaryDirectory(dir=ROOT) as tmp:
        store = Store(Path(tmp) / "j.sqlite")
        link = ReplayLink(rows, setup.machine)
        s = Session(setup, link, store, Path(tmp) / "reports", prepare=prepare_from_rows(rows))
        marks: dict[str, float] = {}
        # the report is rendered after the run's end (IDLE), its end published as IDLE again
        s.listeners.append(lambda st: marks.setdefault(
            "report" if (st["verdict"] or {}).get("report_state") in ("written", "failed")
            else st["state"], time.perf_counter()))
        sampler = asyncio.create_task(sample())
        t0 = time.perf_counter()
        s.start("cli")
        await s.wait()
        t_end = time.perf_counter()
        sampler.cancel()
        store.close()
    n = len(rows)
    cap = marks["IDENTIFY"] - marks["STREAM"]
    print(f"session, 175 poses ({n} touches, replayed at once): capture {cap:.2f} s = "
          f"{cap / n * 1e3:.2f} ms per touch of daemon work (journal FULL + progress); "
          f"identify {marks['JUDGE'] - marks['IDENTIFY']:.2f} s, report "
          f"{marks['report'] - marks['IDLE']:.2f} s after the run's end, whole run "
          f"{t_end - t0:.1f} s; "
          f"state {s.state} {s.reason}")
    print(f"resident memory during the 175-pose run: peak {peak[0]:.0f} MB "
          f"(process at start {rss0:.0f} MB)")


async def bench_transport(transport: str, time_scale: float = 0.1) -> None:
    """Capture wall time minus the simulator's scaled machine time, per touch (7-pose plan)."""
    from benchmarks.rigs.daemon_helpers import thesis_setup
    from benchmarks.rigs.sim_wiring import sim_link
    from daemon.machines.setup import MachineSetup
    from daemon.run.session import Session
    from daemon.service.service import make_link
    from daemon.store.journal import Store
    from simulators.controller import VirtualController
    from simulators.truth import TruthModel

    setup = thesis_setup()
    truth = TruthModel.from_files(CONFIG / "machines/thesis_wcbxfzyt.yaml",
                                  CONFIG / "artefacts/thesis_4ball.yaml",
                                  CONFIG / "errors/thesis_tableB2.yaml")
    ctrl = VirtualController(truth, time_scale=time_scale, dialect=setup.dialect)
    try:
        cfg, stop = await sim_link(transport, ctrl)
    except Exception as e:
        print(f"{transport}: not measured ({type(e).__name__}: {e})")
        return
    try:
        ms = MachineSetup(**{**setup.__dict__, "link": cfg})
        link = make_link(ms)
        await link.connect()
        with tempfile.TemporaryDirectory(dir=ROOT) as tmp:
            store = Store(Path(tmp) / "j.sqlite")
            s = Session(ms, link, store, Path(tmp) / "reports")
            marks: dict[str, float] = {}
            machine_s: list[float] = []

            def mark(st: dict) -> None:
                marks.setdefault(st["state"], time.perf_counter())
                if st["state"] == "IDENTIFY":  # before a DNC verdict program resets the clock
                    machine_s.append(ctrl.machine_time_s)
            s.listeners.append(mark)
            s.start("cli")
            await s.wait()
            store.close()
        await link.close()
        if "IDENTIFY" not in marks:
            print(f"{transport}: run ended {s.state}: {s.reason}")
            return
        wall = marks["IDENTIFY"] - marks["STREAM"]
        sim = machine_s[0] * time_scale
        n = s.total
        print(f"{transport}: {n} touches, capture {wall:.2f} s vs simulated machine time "
              f"{machine_s[0]:.1f} s × {time_scale:g} = {sim:.2f} s → overhead "
              f"{(wall - sim) / n * 1e3:.1f} ms per touch (target ≤ 20 ms)")
    finally:
        await stop()


def bench_demo() -> None:
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "demos.e2e"], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    verdict = next((ln for ln in p.stdout.splitlines() if ln.startswith("verdict")), p.stderr)
    print(f"demo (python -m demos.e2e): {time.perf_counter() - t:.1f} s wall, exit "
          f"{p.returncode}; {verdict.strip()}")


def main() -> None:
    sys.path.insert(0, str(ROOT))  # tests.* helpers (synthetic logs, replay link)
    bench_journal()
    asyncio.run(bench_session_175())
    for transport in ("opcua", "modbus", "serial"):
        asyncio.run(bench_transport(transport))
    bench_demo()


if __name__ == "__main__":
    main()
