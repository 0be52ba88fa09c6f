"""Simulator throughput: offline runs of the thesis 14-pose and 175-pose plans at time scale 0
(target ≤ 5 s wall for 14 poses × 4 balls × 5 touches), simulated machine time, peak memory."""

from __future__ import annotations

import asyncio
import time

from contracts.setup_files import load_artefact, load_machine, load_plan
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.offline import run_program
from simulators.truth import TruthModel

MACHINE = "config/machines/thesis_wcbxfzyt.yaml"
ARTEFACT = "config/artefacts/thesis_4ball.yaml"
ERRORS = "config/errors/thesis_tableB2.yaml"
EFFECTS = "config/errors/thesis_effects_demo.yaml"
PLANS = [("thesis annex B, 14 poses", "config/plans/thesis_annexB_14poses.yaml", 5.0),
         ("thesis ch. 4 grid, 175 poses", "config/plans/thesis_ch4_175poses.yaml", None)]


def bench(plan_path: str, dialect: str = "fanuc", errors: str = ERRORS,
          memory: bool = False) -> dict:
    machine, mf = load_machine(MACHINE)
    artefact = load_artefact(ARTEFACT)
    plan = load_plan(plan_path)
    t0 = time.perf_counter()
    prog = build_program(machine, mf, artefact, plan)
    dia = get_dialect(dialect)
    text, files = dia.render(prog), dia.aux_files(prog)
    t_gen = time.perf_counter() - t0
    truth = TruthModel.from_files(MACHINE, ARTEFACT, errors)
    res = asyncio.run(run_program(truth, text, dialect, files=files, seed=1))
    # Memory in a second run: tracemalloc slows Python down several-fold.
    mem = asyncio.run(run_program(truth, text, dialect, files=files, seed=1,
                                  measure_memory=True)) if memory else res
    return {"touches": len(res.controller.touches), "logged": len(res.rows),
            "state": res.state, "alarm": res.alarm, "wall_s": res.wall_s, "gen_s": t_gen,
            "machine_time_s": res.machine_time_s, "peak_mb": mem.peak_memory_mb or 0.0,
            "blocks": text.count("\n")}


def main() -> None:
    for label, path, target in PLANS:
        r = bench(path, memory=True)
        verdict = "" if target is None else (
            f"  [target ≤ {target:g} s: {'met' if r['wall_s'] <= target else 'MISSED'}]")
        print(f"{label}: {r['touches']} touches ({r['logged']} logged, {r['state']}"
              f"{', ' + r['alarm'] if r['alarm'] else ''}), {r['blocks']} blocks")
        print(f"  simulator wall {r['wall_s']:.2f} s{verdict}; program generation "
              f"{r['gen_s']:.2f} s (not the simulator)")
        print(f"  simulated machine time {r['machine_time_s']:.0f} s "
              f"({r['machine_time_s'] / 60:.1f} min); "
              f"{1e3 * r['wall_s'] / max(r['touches'], 1):.2f} ms wall per touch; "
              f"peak traced memory {r['peak_mb']:.1f} MiB")
    # Position-dependent motion errors: every contact is root-found on the exact chain.
    r = bench(PLANS[0][1], errors=EFFECTS)
    print(f"14 poses with effects ({EFFECTS}): wall {r['wall_s']:.2f} s, {r['state']}")
    for d in ("haas", "linuxcnc", "siemens"):
        print(f"14 poses, {d}: wall {bench(PLANS[0][1], dialect=d)['wall_s']:.2f} s")


if __name__ == "__main__":
    main()
