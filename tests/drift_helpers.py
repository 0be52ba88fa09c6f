"""The shift plan's estimate visits with their times, for the drift-aware identification tests
(tests/test_drift_model.py, tests/test_drift_scatter.py)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contracts.setup_files import load_artefact, load_machine, load_plan
from identification.kinematics import Machine
from identification.model import Artefact
from simulators.exact_log import THESIS_LINKS_UM_URAD, Truth, to_internal

SIGMA = np.array([0.66, 0.98, 0.44])  # thesis §3.4 centre repeatability, µm
RUN_S, BALL_S = 223.0, 3.7  # the shift plan's run (14 poses + the revisit) and between balls, s


@dataclass(frozen=True)
class ShiftVisits:
    """The estimate visits of config/plans/shift_start_14poses.yaml (7 poses + the revisit of
    the first) in run order; per centre row (visit-major, ball-minor) its pose index, ball
    index and time, s."""

    machine: Machine
    artefact: Artefact
    visits: list[tuple[float, float]]  # (B, C), deg
    pose: np.ndarray
    ball: np.ndarray
    t_s: np.ndarray


def shift_visits() -> ShiftVisits:
    """The visits at the times of the plan's 223 s run of 15 visits (its 14 poses, then the
    revisit of the first): visit i at i·223/15 s, the balls of a visit 3.7 s apart."""
    m, _ = load_machine("config/machines/thesis_wcbxfzyt.yaml")
    a = load_artefact("config/artefacts/thesis_4ball.yaml")
    plan = load_plan("config/plans/shift_start_14poses.yaml")
    est = [i for i, p in enumerate(plan.poses) if p.role == "estimate"]
    visits = [(plan.poses[i].b_deg, plan.poses[i].c_deg) for i in est]
    visits.append(visits[0])
    n = len(a.balls)
    pose = np.repeat([*est, est[0]], n)
    t = np.repeat(np.array([*est, len(plan.poses)]) * RUN_S / (len(plan.poses) + 1), n) \
        + np.tile(np.arange(n) * BALL_S, len(visits))
    return ShiftVisits(m, a, visits, pose, np.tile(np.arange(n), len(visits)), t)


def thesis_truth() -> Truth:
    """The thesis links (simulators/exact_log.py) with a small setup offset and scale."""
    return Truth(to_internal(THESIS_LINKS_UM_URAD), np.full((4, 3), 0.02),
                 np.array([0.01, -0.01, 0.02]))
