"""What the gap-diagnosis tests share: the thesis annex-B setup, a seeded truth, touch rows from
simulated touch data, and a `rumba gap` run on a log."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from contracts.probing_log import LogRow, write_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.cli.main import main
from identification.gap import TouchData
from identification.gap.simlog import Truth
from identification.kinematics import Machine
from identification.model import Artefact

CONFIG = Path(__file__).resolve().parents[2] / "config"
MACHINE = CONFIG / "machines/thesis_wcbxfzyt.yaml"
ARTEFACT = CONFIG / "artefacts/thesis_4ball.yaml"
STYLUS_R = 3.0
EXAMPLE = CONFIG / "examples/thesis_annexB_14poses.csv"  # the shipped example log
THESIS_LINKS = {"EB0Z": -12e-6, "EA0Y": -24e-6, "EC0Y": 17e-6, "EC0B": -23e-6, "EA0B": 2e-6,
                "EA0C": -19e-6, "EB0C": 26e-6, "EX0C": -0.106}  # thesis Table B.2


def annex_b_setup() -> tuple[Machine, Artefact, list[tuple[float, float]]]:
    """The thesis machine, its 4-ball artefact and the (B, C) poses of the annex-B plan."""
    machine, _ = load_machine(MACHINE)
    artefact = load_artefact(ARTEFACT)
    plan = load_plan(CONFIG / "plans/thesis_annexB_14poses.yaml")
    return machine, artefact, [(p.b_deg, p.c_deg) for p in plan.poses]


def gap_truth(artefact: Artefact, seed: int = 1, **kw) -> Truth:
    """The thesis link errors with seeded setup errors (``kw``: effects, pose offsets …)."""
    rng = np.random.default_rng(seed)
    return Truth(dict(THESIS_LINKS), rng.normal(0, 0.2, (len(artefact.balls), 3)),
                 rng.normal(0, 0.05, 3), **kw)


def log_rows(data: TouchData, artefact: Artefact, run: str = "r1") -> list[LogRow]:
    """Simulated touches as probing-log rows (read-back rotary = commanded, feed 300)."""
    out = []
    for i in range(len(data)):
        x, y, z = data.xyz_mm[i]
        d = data.direction[i]
        out.append(LogRow(run, i, float(data.t_s[i]), int(data.repeat[i]), int(data.pose[i]),
                          float(data.b_deg[i]), float(data.c_deg[i]),
                          artefact.ids[int(data.ball[i])], int(data.touch[i]), float(d[0]),
                          float(d[1]), float(d[2]), float(x), float(y), float(z),
                          float(data.b_deg[i]), float(data.c_deg[i]), 300.0))
    return out


def gap_json(log: Path, rows: Iterable[LogRow], out: Path) -> dict:
    """Write ``rows`` to ``log``, run `rumba gap` on it (thesis machine and artefact) with the
    JSON report to ``out``; the report."""
    write_log(log, rows)
    assert main(["gap", "--log", str(log), "--machine", str(MACHINE), "--artefact",
                 str(ARTEFACT), "--json", str(out)]) == 0
    return json.loads(out.read_text())


def scatter_components(rep: dict) -> dict[str, dict]:
    """The visit-scatter components of a gap report, by name ("index C", "centre x" …)."""
    return {c["component"]: c for c in rep["scatter"]["components"]}
