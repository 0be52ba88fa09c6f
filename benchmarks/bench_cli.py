"""Speed of the command line, by hand: help, an argument error, analyze and
gap of the 14-pose example log, gcode of 14 poses, analyze of 175 poses — CPU and wall."""

# .venv/bin/python -m benchmarks.bench_cli [--runs 5] [--keep DIR]   (also in `make bench`)
#
# Every command is timed from the shell (a fresh ``rumba`` process each run, the installed script
# of the venv or ``python -m daemon.cli`` without one), so the figures include interpreter
# start-up and imports; median and best of ``--runs`` runs, wall time and CPU time (user + system
# of the child, from its rusage: what the command costs whatever else the computer does). Targets
# (CPU): analyze of the 14-pose example ≤ 0.6 s, of 4 balls × 175 poses ≤ 1.5 s, gap ≤ 2 × its
# analyze, gcode of 14 poses ≤ 0.6 s; an argument error ≤ 0.2 s wall.

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MACHINE = ROOT / "config/machines/thesis_wcbxfzyt.yaml"
ARTEFACT = ROOT / "config/artefacts/thesis_4ball.yaml"
PLAN = ROOT / "config/plans/thesis_ch4_175poses.yaml"
BALL_SETUP_UM = [[120.0, -240.0, 310.0], [-180.0, 90.0, -150.0],
                 [260.0, 140.0, 80.0], [-70.0, -310.0, 200.0]]
PROBE_SETUP_UM = [85.0, -40.0, 150.0]
EXAMPLE_LOG = ROOT / "config/examples/thesis_annexB_14poses.csv"
PLAN_14 = ROOT / "config/plans/thesis_annexB_14poses.yaml"
VALIDATE_14 = "3,4,5,7,9,10,11"  # annex B's held-out poses, as in the README's example


def write_175_pose_log(out: Path) -> int:
    """The thesis machine with Table B.2 link errors probed at the 175 poses (fixed seed: the
    same file byte for byte every time); returns the number of touches."""
    import numpy as np

    from contracts.probing_log import write_log
    from contracts.setup_files import load_artefact, load_machine, load_plan
    from simulators.exact_log import (
        THESIS_LINKS_UM_URAD,
        Truth,
        make_rows,
        thesis_noise,
        to_internal,
    )

    machine, _ = load_machine(MACHINE)
    artefact = load_artefact(ARTEFACT)
    plan = load_plan(PLAN)
    truth = Truth(to_internal(THESIS_LINKS_UM_URAD), np.array(BALL_SETUP_UM) * 1e-3,
                  np.array(PROBE_SETUP_UM) * 1e-3)
    touch, centre = thesis_noise()
    rows = make_rows(machine, artefact, [(p.b_deg, p.c_deg) for p in plan.poses], truth,
                     stylus_radius_mm=plan.stylus_radius_mm, touch_noise_um=touch,
                     centre_noise_um=centre, seed=19175, run_id="bench-175")
    write_log(out, rows)
    return len(rows)


def rumba() -> list[str]:
    """The command as an operator types it: the venv's script, else ``python -m daemon.cli``."""
    script = Path(sys.executable).with_name("rumba")
    return [str(script)] if script.exists() else [sys.executable, "-m", "daemon.cli"]


def _children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def time_command(cmd: list[str], runs: int, expect: int = 0
                 ) -> tuple[list[float], list[float]]:
    """Wall and CPU times (s) of ``runs`` fresh processes of ``cmd`` (one untimed warm-up
    first); each must exit with ``expect``."""
    def once() -> None:
        code = subprocess.run(cmd, cwd=ROOT, capture_output=True).returncode
        if code != expect:
            raise SystemExit(f"{' '.join(cmd)}: exit {code}, expected {expect}")

    once()
    wall, cpu = [], []
    for _ in range(runs):
        c, t = _children_cpu_s(), time.perf_counter()
        once()
        wall.append(time.perf_counter() - t)
        cpu.append(_children_cpu_s() - c)
    return wall, cpu


def _line(label: str, times: tuple[list[float], list[float]], target: str) -> str:
    wall, cpu = times
    return (f"{label}: CPU median {statistics.median(cpu) * 1e3:.0f} ms (best "
            f"{min(cpu) * 1e3:.0f}), wall median {statistics.median(wall) * 1e3:.0f} ms (best "
            f"{min(wall) * 1e3:.0f}) over {len(cpu)} runs (target {target})")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="timed runs of each command")
    ap.add_argument("--keep", type=Path, metavar="DIR",
                    help="write the log, JSON and printed output here (default: a temp dir)")
    args = ap.parse_args([] if argv is None else argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        log = work / "thesis_175poses.csv"
        n = write_175_pose_log(log)
        base = rumba()
        runs = args.runs
        print(_line("rumba --help", time_command([*base, "--help"], runs), "≤ 200 ms wall"))
        print(_line("rumba analyze --help", time_command([*base, "analyze", "--help"], runs),
                    "≤ 200 ms wall"))
        print(_line("argument error (analyze, a log that does not exist)", time_command(
            [*base, "analyze", "--log", str(work / "missing.csv"), "--machine", str(MACHINE),
             "--artefact", str(ARTEFACT)], runs, expect=2), "≤ 200 ms wall"))
        example = ["--log", str(EXAMPLE_LOG), "--machine", str(MACHINE), "--artefact",
                   str(ARTEFACT)]
        print(_line("rumba analyze, 14-pose example log (annex B split)", time_command(
            [*base, "analyze", *example, "--validate-poses", VALIDATE_14, "--json",
             str(work / "example.json")], runs), "≤ 600 ms CPU"))
        print(_line("rumba gap, 14-pose example log", time_command(
            [*base, "gap", *example, "--json", str(work / "gap.json")], runs),
            "≤ 2 × its analyze, CPU"))
        print(_line("rumba gcode, 14 poses (thesis plan, fanuc)", time_command(
            [*base, "gcode", "--machine", str(MACHINE), "--artefact", str(ARTEFACT), "--plan",
             str(PLAN_14), "--dialect", "fanuc", "-o", str(work / "p.nc")], runs),
            "≤ 600 ms CPU"))
        cmd = [*base, "analyze", "--log", str(log), "--machine", str(MACHINE),
               "--artefact", str(ARTEFACT), "--json", str(work / "analysis.json")]
        print(_line(f"rumba analyze, 4 balls × 175 poses ({n} touches)",
                    time_command(cmd, runs), "≤ 1500 ms CPU"))
        if args.keep:
            out = subprocess.run(cmd, cwd=ROOT, capture_output=True, check=True, text=True)
            (work / "analysis.txt").write_text(out.stdout, encoding="utf-8")


if __name__ == "__main__":
    main(sys.argv[1:])
