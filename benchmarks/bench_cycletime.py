"""Cycle time of the thesis 14-pose plan (4 balls, rapid 20 m/min, probing 300 mm/min) against
its targets (≤ 10 min, ≤ 1.5 × the lower bound) and generation + safety-check time of the
175-pose plan; the head families' shipped plans per dialect (straight transits at rapid
where the rapid is a straight line). Run: ``python -m benchmarks cycletime``."""

from __future__ import annotations

import time
from pathlib import Path

from contracts.setup_files import load_artefact, load_machine, load_plan
from programs.cycletime import estimate
from programs.dialects import DIALECTS, get_dialect
from programs.safety import check_program
from programs.toolpath import build_program

CONFIG = Path(__file__).resolve().parent.parent / "config"


def _load(plan: str):
    machine, mf = load_machine(CONFIG / "machines" / "thesis_wcbxfzyt.yaml")
    return machine, mf, load_artefact(CONFIG / "artefacts" / "thesis_4ball.yaml"), \
        load_plan(CONFIG / "plans" / f"{plan}.yaml")


def main() -> None:
    machine, mf, art, plan = _load("thesis_annexB_14poses")
    assert mf.dynamics.rapid_mm_min == 20000 and plan.feeds.probe_mm_min == 300
    prog = build_program(machine, mf, art, plan)
    ct = estimate(prog)
    ok_time = ct.estimate_s <= 600
    ok_ratio = ct.ratio <= 1.5
    print(f"thesis 14 poses × 4 balls = {len(prog.touches)} touches: {ct.summary()}")
    print("  parts: " + ", ".join(f"{k} {v:.1f} s" for k, v in ct.parts_s.items()))
    print(f"  target ≤ 10 min: {'met' if ok_time else 'MISSED'}; "
          f"≤ 1.5 × lower bound: {'met' if ok_ratio else 'MISSED'}")

    machine, mf, art, plan = _load("thesis_ch4_175poses")
    t0 = time.perf_counter()
    prog = build_program(machine, mf, art, plan)
    t1 = time.perf_counter()
    report = check_program(prog)  # raises SafetyError if the shipped plan were unsafe
    ct = estimate(prog)  # once: every dialect prints the same estimate in its header
    t2 = time.perf_counter()
    texts = {name: get_dialect(name).render(prog, ct) for name in sorted(DIALECTS)}
    t3 = time.perf_counter()
    print(f"thesis 175 poses: {len(prog.touches)} touches, {len(prog.moves)} blocks; "
          f"tool path {t1 - t0:.2f} s, safety check + cycle time {t2 - t1:.2f} s "
          f"({report.segments} segments), render 4 dialects {t3 - t2:.2f} s "
          f"({', '.join(f'{k} {len(v) / 1e6:.1f} MB' for k, v in texts.items())}); "
          f"{ct.summary()}")

    heads()


def heads() -> None:
    """The head families' shipped plans, cycle time per dialect with the
    checked straight transits at the max feed (before) and at rapid where the dialect's rapid
    is a straight line (after: Siemens RTLION, Heidenhain L FMAX, LinuxCNC G0)."""
    art = load_artefact(CONFIG / "artefacts" / "vertical_4ball.yaml")
    for mname, pname in (("swivelhead_wcfxyzbt", "swivelhead_12poses"),
                         ("forkhead_wxfyzcat", "forkhead_11poses"),
                         ("nutating_wcbyfxzt", "nutating_12poses")):
        machine, mf = load_machine(CONFIG / "machines" / f"{mname}.yaml")
        prog = build_program(machine, mf, art, load_plan(CONFIG / "plans" / f"{pname}.yaml"))
        before = estimate(prog)
        print(f"{pname}: {len(prog.touches)} touches, before (transits at "
              f"{mf.dynamics.max_feed_mm_min:g} mm/min): {before.summary()}")
        for name in sorted(DIALECTS):
            d = get_dialect(name)
            after = estimate(prog, d.linear_rapid)
            print(f"  {name:<10} {'rapid' if d.linear_rapid else 'feed ':<5} {after.summary()}")


if __name__ == "__main__":
    main()
