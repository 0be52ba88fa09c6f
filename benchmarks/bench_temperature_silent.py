"""What a temperature transmitter switched off but still routable costs a run:
the wall time from the CNC's start request to the verdict on the simulated OPC UA control, with
the spindle channel alone, with a live Modbus TCP transmitter beside it, and with a transmitter
that accepts the connection and never answers (tests/test_temperature_silent.py's socket; its
timeout_s 1 s by default, as in daemon.yaml). Besides the wall time (which the simulated CNC's
own motion dominates: the daemon catches up on buffered results), the time the capture loop
spent in the temperature recorder after the hits (``on_hit``): what held the results up.

    python -m benchmarks.bench_temperature_silent [RUNS] [TIMEOUT_S]
"""

from __future__ import annotations

import asyncio
import statistics
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.rigs.e2e_run import RUN_TIMEOUT_S, wait_verdict_on_cnc
from benchmarks.rigs.rig_helpers import start_rig
from benchmarks.rigs.temperature_helpers import SilentTransmitter, column
from benchmarks.rigs.warm_cnc import SPINDLE, machine_entry, warm_truth, write_config
from daemon.config import load_daemon_config
from daemon.service.service import Service
from daemon.store.temperatures import temperatures
from simulators.controller import VirtualController
from simulators.frontends.transmitter import TransmitterFrontend


async def one(case: str, tmp: Path, timeout_s: float) -> tuple[float, int, float]:
    ctrl = VirtualController(warm_truth())
    rig = await start_rig("opcua", ctrl)
    live = TransmitterFrontend(ctrl)
    silent = SilentTransmitter()
    server = await asyncio.start_server(silent.handle, "127.0.0.1", 0)
    try:
        channels = [{"name": "spindle", "source": "controller", **SPINDLE["opcua"]}]
        if case == "live":
            channels.append(column(await live.start()))
        elif case == "silent":
            channels.append(column(server.sockets[0].getsockname()[1], timeout_s=timeout_s))
        service = Service(load_daemon_config(write_config(tmp, machine_entry(
            rig.link, channels, {}))))
        await service.start()
        try:
            session = service.sessions["mill1"]
            held = [0.0]
            on_hit = session.temps.on_hit

            async def timed(*a: object) -> None:
                t = time.perf_counter()
                await on_hit(*a)  # type: ignore[arg-type]
                held[0] += time.perf_counter() - t

            session.temps.on_hit = timed  # type: ignore[method-assign]
            t0 = time.perf_counter()
            ctrl.raise_start_request()
            await wait_verdict_on_cnc(session, ctrl, RUN_TIMEOUT_S)
            wall = time.perf_counter() - t0
            n = len(temperatures(service.store, session.run_id))
        finally:
            await service.stop()
        return wall, n, held[0]
    finally:
        await silent.close()
        server.close()
        await server.wait_closed()
        if case == "live":
            await live.stop()
        await rig.close()


async def main(runs: int, timeout_s: float) -> None:
    print(f"start request → verdict on the CNC, OPC UA simulator, {runs} runs per case, "
          f"silent transmitter's timeout_s {timeout_s:g}")
    for case in ("spindle only", "live", "silent"):
        walls, helds = [], []
        for _ in range(runs):
            with tempfile.TemporaryDirectory() as d:
                wall, n, held = await one(case, Path(d), timeout_s)
            walls.append(wall)
            helds.append(held)
        print(f"  {case:13s} wall median {statistics.median(walls):6.2f} s (min {min(walls):.2f},"
              f" max {max(walls):.2f}); capture held by the recorder: median "
              f"{statistics.median(helds):.3f} s, max {max(helds):.3f} s; {n} readings/run")


if __name__ == "__main__":
    asyncio.run(main(int(sys.argv[1]) if len(sys.argv) > 1 else 3,
                     float(sys.argv[2]) if len(sys.argv) > 2 else 1.0))
