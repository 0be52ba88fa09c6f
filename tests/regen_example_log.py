"""Regenerate config/examples/thesis_annexB_14poses.csv: `python -m tests.regen_example_log`.

Thesis machine (WCBXFZYT) with the Table B.2 link errors (METHOD.md §5), setup errors of a few
hundred µm, the 4-ball artefact probed at the 14 annex-B poses (plan thesis_annexB_14poses,
6 mm stylus) and the thesis probing repeatability (centre std 0.66 / 0.98 / 0.44 µm, obtained
as in ``simulators.exact_log.thesis_noise``). Fixed seed: the file is reproducible byte for byte.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from contracts.probing_log import write_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from simulators.exact_log import THESIS_LINKS_UM_URAD, Truth, make_rows, thesis_noise, to_internal

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "config" / "examples" / "thesis_annexB_14poses.csv"
BALL_SETUP_UM = [[120.0, -240.0, 310.0], [-180.0, 90.0, -150.0],
                 [260.0, 140.0, 80.0], [-70.0, -310.0, 200.0]]
PROBE_SETUP_UM = [85.0, -40.0, 150.0]


def main(out: Path = OUT) -> None:
    machine, _ = load_machine(ROOT / "config/machines/thesis_wcbxfzyt.yaml")
    artefact = load_artefact(ROOT / "config/artefacts/thesis_4ball.yaml")
    plan = load_plan(ROOT / "config/plans/thesis_annexB_14poses.yaml")
    truth = Truth(to_internal(THESIS_LINKS_UM_URAD), np.array(BALL_SETUP_UM) * 1e-3,
                  np.array(PROBE_SETUP_UM) * 1e-3)
    touch, centre = thesis_noise()
    rows = make_rows(machine, artefact, [(p.b_deg, p.c_deg) for p in plan.poses], truth,
                     stylus_radius_mm=plan.stylus_radius_mm, touch_noise_um=touch,
                     centre_noise_um=centre, seed=20100, run_id="example-annexB")
    write_log(out, rows)
    print(f"wrote {out} ({len(rows)} touches)")


if __name__ == "__main__":
    main()
