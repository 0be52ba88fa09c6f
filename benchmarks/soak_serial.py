"""Soak of the serial DNC end-to-end cases (benchmarks/rigs/e2e_run.py, as the end-to-end
tests run them): every serial transport × dialect, N consecutive rounds in one process,
failures counted (target 0). Not part of ``make test`` nor of ``make bench`` (the name keeps
it out of the benchmark runner): ``.venv/bin/python benchmarks/soak_serial.py --runs 200``."""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


async def _soak(runs: int, cases: list[tuple[str, str]], budget_s: float | None) -> int:
    from benchmarks.rigs.e2e_run import run_start_of_shift
    from benchmarks.rigs.rig_helpers import Rig, make_truth, start_rig
    from daemon.run.session import State
    from simulators.controller import VirtualController

    rigs: dict[str, Rig] = {}
    failures: list[str] = []
    done = 0
    t_start = time.monotonic()
    try:
        for n in range(1, runs + 1):
            for transport, dialect in cases:
                if transport not in rigs:
                    rigs[transport] = await start_rig(
                        transport, VirtualController(make_truth()))
                rig = rigs[transport]
                fe = rig.extra.get("frontend")
                alarms_before = len(fe.alarms) if fe is not None else 0
                with tempfile.TemporaryDirectory() as tmp:
                    t = time.monotonic()
                    try:
                        r = await run_start_of_shift(rig, dialect, Path(tmp))
                        ok = r["state"] == State.IDLE and r["verdict"]["status"] == "PASS"
                        why = "" if ok else f"{r['state']}: {r['reason']} {r['verdict']}"
                    except Exception as e:  # a failed case is counted, the soak goes on
                        ok, why = False, f"{type(e).__name__}: {e}"
                done += 1
                new_alarms = fe.alarms[alarms_before:] if fe is not None else []
                if new_alarms and ok:
                    ok, why = False, f"controller alarm(s) {new_alarms}"
                if not ok:
                    failures.append(f"round {n} {transport}-{dialect}: {why}")
                    print(f"FAIL {failures[-1]}", flush=True)
                    # A fresh simulated CNC: one failure must not cascade into the next cases.
                    await rigs.pop(transport).close()
                peak = f", peak buffer {fe.max_fill}/256" if fe is not None else ""
                print(f"round {n} {transport}-{dialect}: {'ok' if ok else 'FAIL'} "
                      f"{time.monotonic() - t:.1f} s{peak}", flush=True)
            if budget_s is not None and time.monotonic() - t_start > budget_s:
                print(f"time budget {budget_s:g} s spent after round {n}", flush=True)
                break
    finally:
        for rig in rigs.values():
            await rig.close()
    print(f"\n{done} case runs ({len(cases)} cases), {len(failures)} failure(s) in "
          f"{time.monotonic() - t_start:.0f} s")
    for f in failures:
        print(f"  {f}")
    return 1 if failures else 0


def main() -> None:
    sys.path.insert(0, str(ROOT))
    from contracts.result_lines import DIALECT_NAMES

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=200, help="rounds over all serial cases")
    ap.add_argument("--transport", choices=["serial-pty", "serial-socket"], action="append",
                    help="only these transports (default both)")
    ap.add_argument("--dialect", choices=DIALECT_NAMES, action="append",
                    help="only these dialects (default all)")
    ap.add_argument("--budget-s", type=float, default=None,
                    help="stop after the round that exceeds this wall time")
    a = ap.parse_args()
    cases = [(t, d) for t in (a.transport or ["serial-pty", "serial-socket"])
             for d in (a.dialect or DIALECT_NAMES)]
    sys.exit(asyncio.run(_soak(a.runs, cases, a.budget_s)))


if __name__ == "__main__":
    main()
