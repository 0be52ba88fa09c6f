"""``rumba plan`` against the shipped plans, for the thesis machine (fanuc dialect) and the LinuxCNC
sim machine (linuxcnc dialect, two-speed touch): estimated machine time, predicted link
uncertainty, simulated link uncertainty (the std of the link estimates over N offline runs of
the simulator, each analysed as the daemon does, and the mean u those runs report), and the
optimiser's own run time. ``lcnc`` also runs the LinuxCNC pair through LinuxCNC itself once
(local AUTO, as benchmarks/bench_linuxcnc.py) and quotes its wall times.

    .venv/bin/python -m benchmarks plan                   (~12 min: 4 plans × 100 runs)
    .venv/bin/python -m benchmarks.bench_plan 30 thesis   (30 simulated runs, thesis only)

A std from N runs is itself uncertain by 1/√(2(N−1)) (7 % at N = 100, 13 % at 30): the table
prints it.
    .venv/bin/python -m benchmarks.bench_plan lcnc        (+ LinuxCNC: ~8 min, needs LinuxCNC)
"""

from __future__ import annotations

import asyncio
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from contracts.setup_files import load_artefact, load_machine
from daemon.analysis.identify import analyse_centres
from daemon.analysis.touch_centres import rows_to_centres
from programs.plan_make import Outcome, make_plan
from simulators.errors_schema import load_errors
from simulators.offline import run_sync
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parents[1]
C = ROOT / "config"
CASES = {  # name: machine, artefact, targets, errors, dialect, probe sample period (ms)
    "thesis": ("thesis_wcbxfzyt", "thesis_4ball", "shift_start", "thesis_tableB2",
               "fanuc", 0.0),
    # the LinuxCNC servo thread latches every 0.25 ms (config/linuxcnc/README.md): the
    # offline simulator samples its probe input as often, so the feed's effect is the same
    "linuxcnc": ("linuxcnc_xyzbc", "thesis_4ball", "linuxcnc", "linuxcnc_xyzbc",
                 "linuxcnc", 0.25),
}


def _paths(case: str) -> tuple[Path, Path, Path, Path]:
    m, a, t, e, _, _ = CASES[case]
    return (C / "machines" / f"{m}.yaml", C / "artefacts" / f"{a}.yaml",
            C / "plans" / "targets" / f"{t}.yaml", C / "errors" / f"{e}.yaml")


def simulated(case: str, r: Outcome, runs: int) -> dict[str, dict[str, tuple[float, float]]]:
    """Per plan (shipped, optimised) and link: (std of the estimates, mean reported u)."""
    mp, ap, _, ep = _paths(case)
    dialect, sample_ms = CASES[case][4], CASES[case][5]
    machine, mf = load_machine(mp)
    art = load_artefact(ap)
    err = load_errors(ep)
    err = err.model_copy(update={"probe": err.probe.model_copy(
        update={"sample_period_ms": sample_ms})})
    truth = TruthModel.build(machine, mf, art, err)
    out = {}
    for label, plan, g in (("shipped", r.reference, r.old), ("optimised", r.plan, r.new)):
        values: dict[str, list[float]] = {}
        stds: dict[str, list[float]] = {}
        for seed in range(runs):
            res = run_sync(truth, g.text, dialect, seed=1000 + seed)
            if res.state != "done":
                raise RuntimeError(f"{case} {label} seed {seed}: {res.state} {res.alarm}")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                data = rows_to_centres(res.rows, art, plan.stylus_radius_mm)
            a = analyse_centres(machine, art, data, validate_poses=plan.indices("validate"))
            for k, v in a.links.items():
                values.setdefault(k, []).append(float(v.value))
                stds.setdefault(k, []).append(float(v.std or 0.0))
        out[label] = {k: (float(np.std(values[k], ddof=1)), float(np.mean(stds[k])))
                      for k in values}
    out["runs"] = runs  # type: ignore[assignment]
    return out


def report(case: str, r: Outcome, sim: dict | None) -> None:
    print(f"-- {case}: {r.reference.name} vs {r.plan.name} ({CASES[case][4]})")
    print(f"machine time (estimate): {r.old.estimated_s:.0f} s vs {r.new.estimated_s:.0f} s "
          f"= {100 * r.new.estimated_s / r.old.estimated_s:.0f} %; touches "
          f"{len(r.old.touches)} vs {len(r.new.touches)}; optimiser {r.optimiser_s:.1f} s "
          f"({r.chosen.builds} one-pose programs built)")
    print(f"optimised poses (B, C): {[(p.b_deg, p.c_deg) for p in r.plan.poses]} + revisit")
    head = "link    unit  predicted u: shipped  optimised"
    if sim:
        n = sim["runs"]
        head += (f"  | simulated std ({n} runs, ±{100 / np.sqrt(2 * (n - 1)):.0f} %): shipped"
                 "  optimised | reported u: shipped  optimised")
    print(head)
    for k in r.links:
        unit = "µrad" if k[1] in "ABC" else "µm"
        line = f"{k:6}  {unit:4}  {r.ref_u[k]:20.3f}  {r.new_u[k]:9.3f}"
        if sim:
            s, o = sim["shipped"][k], sim["optimised"][k]
            line += f"  | {s[0]:38.3f}  {o[0]:9.3f} | {s[1]:19.3f}  {o[1]:9.3f}"
        print(line)


def through_linuxcnc(r: Outcome) -> None:
    """Both LinuxCNC plans once through LinuxCNC 2.9 (local AUTO run): wall times."""
    if shutil.which("linuxcnc", path="/usr/bin") is None:
        print("LinuxCNC not installed: skipped (bash .ci/install-peers.sh linuxcnc)")
        return
    from benchmarks.bench_linuxcnc import _link, _run
    from daemon.machines.setup import MachineSetup, TriggersFile
    from daemon.machines.tolerances import Tolerances
    from simulators import linuxcnc_peer
    from simulators.hal_probe import write_spec

    mp, ap, _, ep = _paths("linuxcnc")
    m, mf = load_machine(mp)
    art = load_artefact(ap)
    truth = TruthModel.from_files(mp, ap, ep)
    with tempfile.TemporaryDirectory(prefix="rumba-bench-plan.") as tmp:
        spec = Path(tmp) / "spec.json"
        write_spec(truth, spec)
        peer = linuxcnc_peer.up(spec, workdir=Path(tmp) / "peer")
        try:
            for label, plan in (("shipped", r.reference), ("optimised", r.plan)):
                setup = MachineSetup("bench", m, mf, art, plan, "linuxcnc", None,
                                     TriggersFile(), Tolerances(), 60.0,
                                     tuple(plan.indices("validate")), False)
                t0 = time.perf_counter()
                res = asyncio.run(_run(setup, _link("local-auto", peer)))
                print(f"LinuxCNC local AUTO, {label} {plan.name}: {res['touches']} touches, "
                      f"run {res['run_s']:.1f} s (total {time.perf_counter() - t0:.1f} s)")
                for k, v in res["links"].items():
                    want = truth.errors.links.get(k, 0.0)
                    print(f"  {k}: {v['value']:8.2f} ± {v['std']:5.2f} {v['unit']} "
                          f"(injected {want:g})")
        finally:
            linuxcnc_peer.down(peer.dir)


def main(argv: tuple[str, ...] = ()) -> None:
    runs = next((int(a) for a in argv if a.isdigit()), 100)
    for case in [c for c in CASES if c in argv] or CASES:
        mp, ap, tp, _ = _paths(case)
        r = make_plan(mp, ap, tp, CASES[case][4])
        sim = simulated(case, r, runs) if runs > 1 else None
        report(case, r, sim)
        if case == "linuxcnc" and "lcnc" in argv:
            through_linuxcnc(r)


if __name__ == "__main__":
    main(tuple(sys.argv[1:]))
