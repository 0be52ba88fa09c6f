"""The results server of the fuzz (tests/test_opcua_results_fuzz.py) in a process of its own, as
the daemon runs it, so that the fuzzing client's memory and garbage collections do not count as
the server's. Prints one JSON line (url, client certificate and key, journal) when it serves,
then answers ``stats`` on stdin with one JSON line (loop lag monitor, open report files,
tracebacks logged) and ends on ``quit`` or end of input.

    python -m tests.opcua_fuzz_server WORKDIR EXTRA_RUNS
"""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

from tests.opcua_bounds_helpers import LagMonitor, Tracebacks, serve


async def main(work: Path, extra_runs: int) -> None:
    with Tracebacks() as tb:
        served = await serve(work, extra_runs=extra_runs)
        monitor = LagMonitor().start()
        transfer = served.srv.machines["mill1"].transfer
        print(json.dumps({"url": served.url, "cert": str(served.pki["cert"]),
                          "key": str(served.pki["key"]), "db": str(work / "journal.sqlite")}),
              flush=True)
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader()
        await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
        while (line := (await reader.readline()).decode().strip()) not in ("", "quit"):
            if line == "stats":
                print(json.dumps({
                    "wakeups": monitor.wakeups, "stalls": monitor.stalls,
                    "worst_s": monitor.worst_s, "worst_cpu_s": monitor.worst_cpu_s,
                    "stalled_at": monitor.stalled_at,
                    "open": len(transfer.open), "released": transfer.released,
                    "tracebacks": tb.lines()}), flush=True)
        await monitor.stop()
        await served.close()


if __name__ == "__main__":
    asyncio.run(main(Path(sys.argv[1]), int(sys.argv[2])))
