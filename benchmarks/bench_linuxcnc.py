"""A 14-pose verification through LinuxCNC, remote (linuxcncrsh, MDI streaming) and local (the
``linuxcnc`` module, AUTO run of a program file): wall time, time per touch, and the daemon's own
overhead per touch (its CPU time and the time not spent waiting for LinuxCNC), on one LinuxCNC.
Needs LinuxCNC (bash .ci/install-peers.sh linuxcnc); skipped with a note otherwise.

    .venv/bin/python -m benchmarks linuxcnc        (~10 min: 2 x 280 touches)
    .venv/bin/python -m benchmarks.bench_linuxcnc local-auto remote-mdi local-mdi
"""

from __future__ import annotations

import asyncio
import shutil
import sys
import tempfile
import time
from pathlib import Path

from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis import pipeline
from daemon.machines.setup import MachineSetup, TriggersFile
from daemon.machines.tolerances import Tolerances
from drivers.linuxcnc.channel import RshChannel
from drivers.registry import make_link
from simulators import linuxcnc_peer
from simulators.hal_probe import write_spec
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parents[1]
MACHINE = ROOT / "config/machines/linuxcnc_xyzbc.yaml"
ARTEFACT = ROOT / "config/artefacts/thesis_4ball.yaml"
ERRORS = ROOT / "config/errors/linuxcnc_xyzbc.yaml"
PLAN = ROOT / "config/plans/thesis_annexB_14poses.yaml"
VARIANTS = ("remote-mdi", "local-auto")


def _link(variant: str, peer: linuxcnc_peer.Peer) -> dict:
    if variant == "remote-mdi":
        return {"transport": "linuxcnc", "port": peer.port, "prelude_mdi": ["M429"]}
    mode, run = variant.split("-")
    return {"transport": "linuxcnc", "mode": mode, "run": run, "prelude_mdi": ["M429"],
            "local_home": str(peer.dir / "home")}


async def _run(setup: MachineSetup, link_cfg: dict) -> dict:
    waited = [0.0]
    ask = RshChannel.ask

    async def timed_ask(self: RshChannel, cmd: str, timeout_s: float | None = None) -> str:
        t = time.perf_counter()
        try:
            return await ask(self, cmd, timeout_s)
        finally:
            waited[0] += time.perf_counter() - t

    sleep = asyncio.sleep

    async def timed_sleep(delay: float, result: object = None) -> object:
        t = time.perf_counter()  # the link's polls wait for LinuxCNC's motion
        try:
            return await sleep(delay, result)
        finally:
            waited[0] += time.perf_counter() - t

    RshChannel.ask = timed_ask  # type: ignore[method-assign]
    asyncio.sleep = timed_sleep  # type: ignore[assignment]
    link = make_link(link_cfg)
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        prepared = pipeline.prepare(setup, "bench")
        t_prep = time.perf_counter() - t0
        hits = []
        t1, c1, w1 = time.perf_counter(), time.process_time(), waited[0]
        async for h in link.run(prepared.job):
            hits.append(prepared.complete(h, time.perf_counter() - t1))
        t_run, c_run = time.perf_counter() - t1, time.process_time() - c1
        w_run = waited[0] - w1
        t2 = time.perf_counter()
        analysis = pipeline.analyse(setup, hits, "bench")
        t_an = time.perf_counter() - t2
        return {"touches": len(hits), "blocks": link.blocks_sent, "prepare_s": t_prep,
                "run_s": t_run, "analyse_s": t_an, "cpu_run_s": c_run, "io_wait_s": w_run,
                "total_s": time.perf_counter() - t0, "cpu_total_s": time.process_time() - c0,
                "links": analysis.data.to_json()["links"]}
    finally:
        RshChannel.ask = ask  # type: ignore[method-assign]
        asyncio.sleep = sleep  # type: ignore[assignment]
        await link.close()


def main(variants: tuple[str, ...] = VARIANTS) -> None:
    if shutil.which("linuxcnc", path="/usr/bin") is None:
        print("LinuxCNC not installed: skipped (bash .ci/install-peers.sh linuxcnc)")
        return
    unknown = [v for v in variants if v not in ("remote-mdi", "local-mdi", "local-auto")]
    if unknown:
        print(f"unknown variants {unknown}: remote-mdi, local-mdi, local-auto")
        return
    m, mf = load_machine(MACHINE)
    plan = load_plan(PLAN)
    setup = MachineSetup("bench", m, mf, load_artefact(ARTEFACT), plan, "linuxcnc", None,
                         TriggersFile(), Tolerances(), 60.0, tuple(plan.indices("validate")),
                         False)
    truth = TruthModel.from_files(MACHINE, ARTEFACT, ERRORS)
    results = {}
    with tempfile.TemporaryDirectory(prefix="rumba-bench-lcnc.") as tmp:
        spec = Path(tmp) / "spec.json"
        write_spec(truth, spec)
        t0 = time.perf_counter()
        peer = linuxcnc_peer.up(spec, workdir=Path(tmp) / "peer")
        t_up = time.perf_counter() - t0
        try:
            for v in variants:
                results[v] = asyncio.run(_run(setup, _link(v, peer)))
        finally:
            t1 = time.perf_counter()
            linuxcnc_peer.down(peer.dir)
            t_down = time.perf_counter() - t1
    print(f"plan {plan.name}; LinuxCNC up {t_up:.1f} s, down {t_down:.1f} s")
    for v, r in results.items():
        n = max(r["touches"], 1)
        print(f"-- {v}: {r['touches']} touches, {r['blocks']} MDI blocks "
              f"({r['blocks'] / n:.1f} per touch)")
        print(f"prepare {r['prepare_s']:.2f} s | run+capture {r['run_s']:.1f} s "
              f"({r['run_s'] / n:.3f} s/touch) | identify {r['analyse_s']:.2f} s | "
              f"total {r['total_s']:.1f} s")
        print(f"daemon overhead per touch: CPU {r['cpu_run_s'] / n * 1e3:.1f} ms, not waiting "
              f"for LinuxCNC {(r['run_s'] - r['io_wait_s']) / n * 1e3:.1f} ms "
              f"(of {r['run_s'] / n * 1e3:.0f} ms)")
        for name, val in r["links"].items():
            want = truth.errors.links.get(name, 0.0)
            print(f"  {name}: {val['value']:8.2f} ± {val['std']:5.2f} {val['unit']} "
                  f"(injected {want:g}, {abs(val['value'] - want) / val['std']:.1f} u)")
    if len(results) > 1:
        base = results[variants[0]]["run_s"]
        print("run time vs " + variants[0] + ": " + ", ".join(
            f"{v} {r['run_s'] / base:.2f}x" for v, r in results.items()))


if __name__ == "__main__":
    main(tuple(sys.argv[1:]) or VARIANTS)
