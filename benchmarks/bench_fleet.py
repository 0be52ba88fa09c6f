"""Fleet figures: N daemons × M touches into one PostgreSQL at once (hits/s, per-hit latency
from the local commit to the PostgreSQL commit p50/p99, nothing lost or duplicated) and the
MQTT publish latency per state change, on real servers (simulators/fleet_peers.py).

    python -m benchmarks.bench_fleet [DAEMONS] [TOUCHES]     (default 20 300)
"""

from __future__ import annotations

import asyncio
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psycopg

from contracts.messages import ProbeHit


def _hit(seq: int) -> ProbeHit:
    return ProbeHit(seq=seq, pose=seq // 20, ball="B1", touch=1 + seq % 5,
                    axes={"X": 1.5 * seq, "Y": -2.0, "Z": 3.25, "B": 30.0, "C": 60.0},
                    triggered=True, t_s=0.1 * seq, raw=f"#{seq}", direction=(1.0, 0, 0),
                    feed_mm_min=300.0, extra={})


async def _daemon(dsn: str, k: int, touches: int, tmp: str, go: float) -> list[float]:
    from daemon.store import Store
    from daemon.store_drain import Drainer
    from daemon.store_pg import PgStore

    store = Store(Path(tmp) / f"d{k}.sqlite")
    drainer = Drainer(store, dsn, app=f"bench{k}")
    local: dict[int, float] = {}
    lat: list[float] = []
    write = PgStore.write_run

    async def timed(self, b):  # type: ignore[no-untyped-def]
        await write(self, b)
        now = time.perf_counter()
        lat.extend(now - local[h[1]] for h in b.hits if h[1] in local)

    PgStore.write_run = timed  # type: ignore[method-assign]
    await drainer.drain()
    drainer.start()
    while time.time() < go:
        await asyncio.sleep(0.001)
    rid = f"B{k:03d}-{int(go)}"
    store.new_run(rid, f"mill{k:03d}", "cnc", touch_total=touches)
    for seq in range(1, touches + 1):
        store.journal_hit(rid, _hit(seq))
        local[seq] = time.perf_counter()
        await asyncio.sleep(0)  # the loop runs the drainer between touches, as in a daemon
    store.set_state(rid, "DONE")
    while drainer.backlog():
        await asyncio.sleep(0.005)
    await drainer.stop()
    store.close()
    return lat


def _worker(dsn: str, k: int, touches: int, tmp: str, go: float) -> None:
    """One daemon process: prints its per-hit latencies (s) as JSON on stdout."""
    print(json.dumps(asyncio.run(_daemon(dsn, k, touches, tmp, go))))


def store_bench(daemons: int, touches: int) -> None:
    from simulators.fleet_peers import PostgresPeer

    pg = PostgresPeer(fsync=True, max_connections=daemons + 20)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            go = time.time() + 2.0 + 0.3 * daemons  # every process started and connected
            procs = [subprocess.Popen(
                [sys.executable, "-c", "import sys; from benchmarks.bench_fleet import _worker;"
                 f" _worker({pg.dsn!r}, {k}, {touches}, {tmp!r}, {go!r})"],
                stdout=subprocess.PIPE, text=True) for k in range(daemons)]
            lats = [json.loads(p.communicate(timeout=600)[0]) for p in procs]
            wall = time.time() - go
        with psycopg.connect(pg.dsn) as c:
            n, distinct = c.execute("SELECT COUNT(*), COUNT(DISTINCT (run_id, seq)) FROM hits"
                                    ).fetchone()  # type: ignore[misc]
        allv = sorted(x for lat in lats for x in lat)
        q = statistics.quantiles(allv, n=100)
        print(f"fleet store: {daemons} daemons × {touches} touches → {n} hits in PostgreSQL "
              f"({distinct} distinct; expected {daemons * touches}); "
              f"{len(allv)} latencies; local commit → PostgreSQL commit p50 {q[49]*1e3:.1f} ms, "
              f"p99 {q[98]*1e3:.1f} ms, max {allv[-1]*1e3:.1f} ms; "
              f"{n / wall:.0f} hits/s (burst of {wall:.2f} s from the common start to the "
              "last daemon's exit)")
    finally:
        pg.close()


async def mqtt_bench(messages: int = 300) -> None:
    import aiomqtt

    from daemon.mqtt import MachinePublisher
    from daemon.mqtt_config import MqttConfig
    from daemon.store import Store
    from simulators.fleet_peers import MosquittoPeer

    b = MosquittoPeer()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            store = Store(Path(tmp) / "j.sqlite")
            cfg = MqttConfig("127.0.0.1", b.port, "bench", "rumba", None, None, None, 1, 30,
                             10000, 3600.0)
            pub = MachinePublisher(cfg, "mill1", store)
            pub.start()
            lat: list[float] = []
            async with aiomqtt.Client("127.0.0.1", b.port) as sub:
                await sub.subscribe("rumba/bench/mill1/state", qos=1)
                await asyncio.sleep(0.5)
                for i in range(messages):
                    pub.publish("state", {"state": "CAPTURE", "i": i, "t": time.perf_counter()},
                                retain=True)
                    async for m in sub.messages:
                        d = json.loads(m.payload)
                        if d.get("i") == i:
                            lat.append(time.perf_counter() - d["t"])
                            break
            await pub.stop()
            store.close()
        q = statistics.quantiles(lat, n=100)
        print(f"mqtt: {messages} state changes, QoS 1 retained, publish() → subscriber "
              f"p50 {q[49]*1e3:.2f} ms, p99 {q[98]*1e3:.2f} ms")
    finally:
        b.close()


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    daemons = int(argv[0]) if argv else 20
    touches = int(argv[1]) if len(argv) > 1 else 300
    store_bench(daemons, touches)
    asyncio.run(mqtt_bench())


if __name__ == "__main__":
    main()
