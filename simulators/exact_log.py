"""Exact synthetic probing logs (no probe physics; simulators/controller.py is the full twin).

For every pose and ball the true centre is the controller X, Y, Z that puts the true stylus tip
on the true ball centre (``kinematics.solve_centre`` with the true links, setup and scale); the
five stylus-centre points lie on the sphere of radius ball + stylus radius around it, along the
nominal touch directions (touch point = centre − d·(R + r),
``contracts.messages.TOUCH_DIRECTIONS``).
Noise: ``touch_noise_um`` along each touch direction (trigger scatter) plus ``centre_noise_um``
(x, y, z) common to the five touches of a group (repositioning); see ``thesis_noise``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from contracts.messages import TOUCH_DIRECTIONS
from contracts.probing_log import LogRow
from identification.kinematics import ChainState, Machine, rotary_columns, solve_centre
from identification.model import Artefact

THESIS_LINKS_UM_URAD = {"EB0Z": -12.0, "EA0Y": -24.0, "EC0Y": 17.0, "EC0B": -23.0,
                        "EA0B": 2.0, "EA0C": -19.0, "EB0C": 26.0, "EX0C": -106.0}
"""Thesis Table B.2 (METHOD.md §5), µrad for rotations, µm for the offset EX0C."""


def to_internal(links_um_urad: Mapping[str, float]) -> dict[str, float]:
    """µm / µrad → mm / rad by ISO name (E[XYZ]… translation, E[ABC]… rotation)."""
    return {k: v * (1e-6 if k[1] in "ABC" else 1e-3) for k, v in links_um_urad.items()}


def thesis_noise() -> tuple[float, tuple[float, float, float]]:
    """(touch_noise_um, centre_noise_um) giving the thesis centre std 0.66 / 0.98 / 0.44 µm.

    A free-radius fit of 4 equator diagonals + 1 pole turns a touch scatter σ along the
    direction into centre std σ/√2 (x, y) and σ·√1.25 (z); σ = 0.3 µm gives 0.21 / 0.21 /
    0.34 µm, and the common per-group part makes up the rest in quadrature.
    """
    t = 0.3
    tgt = np.array([0.66, 0.98, 0.44])
    own = np.array([t / np.sqrt(2), t / np.sqrt(2), t * np.sqrt(1.25)])
    return t, tuple(float(x) for x in np.sqrt(tgt**2 - own**2))


@dataclass
class Truth:
    links: dict[str, float] = field(default_factory=dict)  # mm / rad
    balls_mm: np.ndarray | None = None  # (n, 3) setup errors
    tip_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 0.0


def true_centres(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
                 truth: Truth) -> np.ndarray:
    """(m, n, 3) controller X, Y, Z of the exact centres."""
    n = len(artefact.balls)
    pb = np.array(poses, float)
    dballs = np.zeros((n, 3)) if truth.balls_mm is None else np.asarray(truth.balls_mm)
    w = np.tile(artefact.nominal_mm + dballs, (len(pb), 1))
    bc = np.repeat(pb, n, axis=0)
    state = ChainState(links=truth.links, tip_offset_mm=np.asarray(truth.tip_mm, float),
                       linear_scale=truth.scale)
    q = solve_centre(machine, rotary_columns(machine, bc[:, 0], bc[:, 1]), w, state)
    return q.reshape(len(pb), n, 3)


def make_rows(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
              truth: Truth, stylus_radius_mm: float = 3.0, touch_noise_um: float = 0.0,
              centre_noise_um: Sequence[float] = (0.0, 0.0, 0.0), seed: int = 0,
              run_id: str = "synth", repeats: int = 1) -> list[LogRow]:
    """Probing-log rows of every pose × ball × touch (× repeat), in probing order."""
    rng = np.random.default_rng(seed)
    centres = true_centres(machine, artefact, poses, truth)
    rows: list[LogRow] = []
    seq, t = 0, 0.0
    for rep in range(repeats):
        for i, (b, c) in enumerate(poses):
            for j, ball in enumerate(artefact.balls):
                r = ball.diameter_mm / 2 + stylus_radius_mm
                common = rng.normal(0.0, 1.0, 3) * np.asarray(centre_noise_um) * 1e-3
                for touch, d in TOUCH_DIRECTIONS.items():
                    d = np.asarray(d)
                    noise = rng.normal(0.0, touch_noise_um * 1e-3)
                    p = centres[i, j] - d * (r + noise) + common
                    seq += 1
                    t += 4.0
                    rows.append(LogRow("synth" if run_id is None else run_id, seq, t, rep, i,
                                       float(b), float(c), ball.id, touch, *map(float, d),
                                       *map(float, p), float(b), float(c), 300.0))
    return rows


def shipped_run_rows(machine_path: Path, artefact_path: Path, plan_path: Path,
                     links_um_urad: Mapping[str, float], *, run_id: str = "synth"
                     ) -> list[LogRow]:
    """The log of a run on shipped setup files with ``links_um_urad`` injected, thesis noise:
    balls and probe tip set up at random (seed 1), the touches' noise seed 3 — the imported
    run of the compensation tests."""
    from contracts.setup_files import load_artefact, load_machine, load_plan

    machine, _ = load_machine(machine_path)
    artefact = load_artefact(artefact_path)
    plan = load_plan(plan_path)
    rng = np.random.default_rng(1)
    truth = Truth(links=to_internal(links_um_urad),
                  balls_mm=rng.normal(0, 0.2, (len(artefact.balls), 3)),
                  tip_mm=rng.normal(0, 0.02, 3))
    tn, cn = thesis_noise()
    return make_rows(machine, artefact, [(p.b_deg, p.c_deg) for p in plan.poses], truth,
                     plan.stylus_radius_mm, tn, cn, seed=3, run_id=run_id)
