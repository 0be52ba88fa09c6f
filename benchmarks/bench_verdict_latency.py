"""Time from a run's last hit to its verdict written back, and to its report."""

# .venv/bin/python -m benchmarks.bench_verdict_latency [--runs 3]
#
# The session on the thesis machine (tests' ReplayLink, no delay between hits), one run after
# another in one process after an untimed warm-up run: last hit → IDLE (verdict journaled,
# judged, written back, the end published) and last hit → report written (the worker's end).
# Once, the report was rendered between JUDGE and WRITE-BACK: the verdict reached
# the CNC at about the second figure.

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import time
from pathlib import Path


async def _one(tmp: Path, i: int) -> tuple[float, float]:
    from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
    from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
    from daemon.run.session import Session
    from daemon.store.journal import Store

    setup = thesis_setup()
    rows = thesis_rows(setup)
    store = Store(tmp / f"j{i}.sqlite")
    s = Session(setup, ReplayLink(rows, setup.machine), store, tmp / "reports",
                prepare=prepare_from_rows(rows))
    marks: dict[str, float] = {}

    def on(st: dict) -> None:
        if st["done"] == st["total"] and st["total"] and "last_hit" not in marks:
            marks["last_hit"] = time.perf_counter()
        if st["state"] == "IDLE" and "idle" not in marks:
            marks["idle"] = time.perf_counter()

    s.listeners.append(on)
    s.start("cli")
    await s.wait()
    done = time.perf_counter()
    store.close()
    return marks["idle"] - marks["last_hit"], done - marks["last_hit"]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="bench_verdict_latency")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args(argv if argv is not None else [])
    with tempfile.TemporaryDirectory() as d:
        asyncio.run(_one(Path(d), -1))  # warm-up: imports, font cache
        got = [asyncio.run(_one(Path(d), i)) for i in range(args.runs)]
    back, rep = [g[0] for g in got], [g[1] for g in got]
    print(f"{args.runs} runs (thesis machine, replayed hits), wall seconds after the last hit:")
    print(f"  verdict written back (IDLE) median {statistics.median(back):5.2f}, "
          f"max {max(back):5.2f}")
    print(f"  report written              median {statistics.median(rep):5.2f}, "
          f"max {max(rep):5.2f}")


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
