"""Fleet figures: N daemons × M touches into one PostgreSQL at once (hits/s, per-hit latency
from the local commit to the PostgreSQL commit p50/p99, the PostgreSQL transaction time, nothing
lost or duplicated), the MQTT publish latency per state change, and the fleet page over 100
machines × 365 daily runs, on real servers (simulators/fleet_peers.py).

    python -m benchmarks.bench_fleet [DAEMONS] [TOUCHES] [TOUCH_INTERVAL_MS]   (20 300 0)

TOUCH_INTERVAL_MS 0 writes touches flat out (each one still a FULL-synchronous SQLite commit,
as in the daemon); a real probe touches every 0.3-2 s.
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
from daemon.store import pg_bulk


def _hit(seq: int) -> ProbeHit:
    return ProbeHit(seq=seq, pose=seq // 20, ball="B1", touch=1 + seq % 5,
                    axes={"X": 1.5 * seq, "Y": -2.0, "Z": 3.25, "B": 30.0, "C": 60.0},
                    triggered=True, t_s=0.1 * seq, raw=f"#{seq}", direction=(1.0, 0, 0),
                    feed_mm_min=300.0, extra={})


async def _daemon(dsn: str, k: int, touches: int, tmp: str, go: float, interval_s: float
                  ) -> dict[str, list[float]]:
    from daemon.store.drain import Drainer
    from daemon.store.journal import Store
    from daemon.store.pg import PgStore

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
        await asyncio.sleep(interval_s)  # the loop runs the drainer between touches
    store.set_state(rid, "DONE")
    while drainer.backlog():
        await asyncio.sleep(0.005)
    await drainer.stop()
    store.close()
    return {"lat": lat, "commit": drainer.commit_s}


def _worker(dsn: str, k: int, touches: int, tmp: str, go: float, interval_s: float) -> None:
    """One daemon process: prints its per-hit latencies and commit times (s) as JSON."""
    print(json.dumps(asyncio.run(_daemon(dsn, k, touches, tmp, go, interval_s))))


def store_bench(daemons: int, touches: int, interval_s: float = 0.0) -> None:
    from simulators.fleet_peers import PostgresPeer

    pg = PostgresPeer(fsync=True, max_connections=daemons + 20)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            go = time.time() + 2.0 + 0.3 * daemons  # every process started and connected
            procs = [subprocess.Popen(
                [sys.executable, "-c", "import sys; from benchmarks.bench_fleet import _worker;"
                 f" _worker({pg.dsn!r}, {k}, {touches}, {tmp!r}, {go!r}, {interval_s!r})"],
                stdout=subprocess.PIPE, text=True) for k in range(daemons)]
            res = [json.loads(p.communicate(timeout=900)[0]) for p in procs]
            lats, commits = [r["lat"] for r in res], sorted(x for r in res for x in r["commit"])
            wall = time.time() - go
        with psycopg.connect(pg.dsn) as c:
            n, distinct = pg_bulk.hit_counts(c)
        allv = sorted(x for lat in lats for x in lat)
        q = statistics.quantiles(allv, n=100)
        qc = statistics.quantiles(commits, n=100) if len(commits) > 1 else [commits[0]] * 99
        print(f"fleet store: {daemons} daemons × {touches} touches, one every "
              f"{interval_s * 1e3:g} ms → {n} hits in PostgreSQL "
              f"({distinct} distinct; expected {daemons * touches}); "
              f"{len(allv)} latencies; local commit → PostgreSQL commit p50 {q[49]*1e3:.1f} ms, "
              f"p99 {q[98]*1e3:.1f} ms, max {allv[-1]*1e3:.1f} ms; "
              f"{n / wall:.0f} hits/s (burst of {wall:.2f} s from the common start to the "
              f"last daemon's exit); {len(commits)} PostgreSQL transactions (one run's batch "
              f"each), commit p50 {qc[49]*1e3:.1f} ms, p99 {qc[98]*1e3:.1f} ms")
    finally:
        pg.close()


async def mqtt_bench(messages: int = 300) -> None:
    import aiomqtt

    from daemon.mqtt.config import MqttConfig
    from daemon.mqtt.publisher import MachinePublisher
    from daemon.store.journal import Store
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
    interval_s = float(argv[2]) / 1e3 if len(argv) > 2 else 0.0
    store_bench(daemons, touches, interval_s)
    asyncio.run(mqtt_bench())
    asyncio.run(page_bench())


LINKS = {"EXOC": "um", "EYOC": "um", "EA0B": "urad", "EB0B": "urad", "EC0B": "urad",
         "EXOB": "um", "EAOC": "urad", "EBOC": "urad"}


async def page_bench(machines: int = 100, days: int = 365, repeats: int = 10) -> None:
    """The fleet table and one machine's year of trend, over the real app and PostgreSQL."""
    import random

    import aiohttp
    from aiohttp import web

    from daemon.fleet.app import create_fleet_app
    from daemon.store.pg import PgStore
    from simulators.fleet_peers import PostgresPeer

    pg = PostgresPeer(fsync=False)
    try:
        store = await PgStore.connect(pg.dsn)  # the schema
        await store.close()
        rnd = random.Random(1)
        now = time.time()
        t0 = time.perf_counter()
        with psycopg.connect(pg.dsn) as c:
            for m in range(machines):
                name = f"mill{m:03d}"
                row = (name, "site", "fanuc", "opcua",
                       json.dumps({"links": {}, "default_um": {"warn": 10, "fail": 20},
                                   "default_urad": {"warn": 30, "fail": 60}}), now)
                runs, est = [], []
                for d in range(days):
                    rid = f"{name}-{d:03d}"
                    start = now - (days - d) * 86400.0
                    verdict = rnd.choice(("PASS",) * 8 + ("WARN", "FAIL"))
                    runs.append((rid, name, "cnc", "DONE", "", "p", "a", "fanuc", 300, start,
                                 start + 240, verdict, f"{verdict}: 10 checks", 0))
                    est.append((rid, json.dumps({"links": {
                        k: {"value": rnd.gauss(0, 8), "std": 1.0, "unit": u, "thesis_name": k}
                        for k, u in LINKS.items()}})))
                pg_bulk.load_history(c, row, runs, est)
            c.commit()
            pg_bulk.analyze(c)
        seeded = time.perf_counter() - t0
        app = create_fleet_app(pg.dsn, "bench-token-0123456789", bind_host="127.0.0.1")
        runner = web.AppRunner(app, handle_signals=False)
        await runner.setup()
        await web.TCPSite(runner, "127.0.0.1", 0).start()
        url = f"http://127.0.0.1:{runner.addresses[0][1]}"
        figures = {}
        async with aiohttp.ClientSession(
                headers={"Authorization": "Bearer bench-token-0123456789"}) as http:
            for what, path in (("fleet table", "/"),
                               ("machine page, 1 year trend", "/machines/mill050?days=365")):
                times, size = [], 0
                for _ in range(repeats + 1):
                    t = time.perf_counter()
                    async with http.get(url + path) as r:
                        body = await r.read()
                        assert r.status == 200, r.status
                    times.append(time.perf_counter() - t)
                    size = len(body)
                times = sorted(times[1:])  # the first opens the store connection
                figures[what] = (statistics.median(times), times[-1], size)
        await runner.cleanup()
        print(f"fleet page over {machines} machines × {days} daily runs "
              f"({machines * days} runs, seeded in {seeded:.1f} s): " + "; ".join(
                  f"{w}: median {m * 1e3:.0f} ms, max {x * 1e3:.0f} ms, {s / 1024:.0f} KiB HTML"
                  for w, (m, x, s) in figures.items()) + " (server render + transfer)")
    finally:
        pg.close()


if __name__ == "__main__":
    main()
