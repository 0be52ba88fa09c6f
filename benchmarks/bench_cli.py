"""Speed of the command line (issue 19), by hand: ``rumba --help`` and the 175-pose analyze."""

# .venv/bin/python -m benchmarks.bench_cli [--runs 7] [--keep DIR]   (also in `make bench`)
#
# Both are timed from the shell (a fresh ``rumba`` process each run, the installed script of the
# venv or ``python -m daemon.cli`` without one), so the figures include interpreter start-up and
# imports; median and best of ``--runs`` runs. Targets: ``--help`` well under 0.5 s, analyze of
# 4 balls × 175 poses (thesis plan ``thesis_ch4_175poses``, 3 500 touches) ≤ 1 s.

from __future__ import annotations

import argparse
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


def write_175_pose_log(out: Path) -> int:
    """The thesis machine with Table B.2 link errors probed at the 175 poses (fixed seed: the
    same file byte for byte every time); returns the number of touches."""
    import numpy as np

    from contracts.probing_log import write_log
    from contracts.setup_files import load_artefact, load_machine, load_plan
    from tests.synth import THESIS_LINKS_UM_URAD, Truth, make_rows, thesis_noise, to_internal

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


def time_command(cmd: list[str], runs: int) -> list[float]:
    """Wall times (s) of ``runs`` fresh processes of ``cmd`` (one untimed warm-up first)."""
    subprocess.run(cmd, cwd=ROOT, capture_output=True, check=True)
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        subprocess.run(cmd, cwd=ROOT, capture_output=True, check=True)
        times.append(time.perf_counter() - t)
    return times


def _line(label: str, times: list[float], target_s: float) -> str:
    return (f"{label}: median {statistics.median(times) * 1e3:.0f} ms, best "
            f"{min(times) * 1e3:.0f} ms over {len(times)} runs (target ≤ {target_s * 1e3:.0f} ms)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7, help="timed runs of each command")
    ap.add_argument("--keep", type=Path, metavar="DIR",
                    help="write the log, JSON and printed output here (default: a temp dir)")
    args = ap.parse_args([] if argv is None else argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        log = work / "thesis_175poses.csv"
        n = write_175_pose_log(log)
        base = rumba()
        print(_line("rumba --help", time_command([*base, "--help"], args.runs), 0.5))
        print(_line("rumba analyze --help", time_command([*base, "analyze", "--help"], args.runs),
                    0.5))
        cmd = [*base, "analyze", "--log", str(log), "--machine", str(MACHINE),
               "--artefact", str(ARTEFACT), "--json", str(work / "analysis.json")]
        print(_line(f"rumba analyze, 4 balls × 175 poses ({n} touches)",
                    time_command(cmd, args.runs), 1.0))
        if args.keep:
            out = subprocess.run(cmd, cwd=ROOT, capture_output=True, check=True, text=True)
            (work / "analysis.txt").write_text(out.stdout, encoding="utf-8")


if __name__ == "__main__":
    main(sys.argv[1:])
