"""Self-check with visit errors: effects under index scatter, null runs with it, knocked balls.

A scenario name with ``SUFFIX`` runs its base scenario on a machine whose rotary axes index with
``SCATTER_URAD`` (1σ per indexation, every rotary axis); the injected effect is scaled to the
self-check's factor × the floor *with* that scatter (else it would drown in it), and the held-out
gap after the effect must be at most ``AFTER_LIMIT_SCATTER`` × the scatter-aware floor (the
issue's acceptance). ``STEP`` knocks one ball by 5-20 µm between two visits with at least
``MIN_SIDE`` visits of it on each side: it must be named with the ball, the moment (± one
pose) and the size (± ``STEP_SIZE_TOL_UM``). ``POLE`` puts a chip of 8-15 µm on the pole touch
of one random ball visit (under the scatter: ``pole_chip+scatter``): the pole only moves the
centre, which the scatter blurs, so it must be named — ``measurement_outlier`` at that visit, or
``pole_defect`` there when it is below what the run can name (``visit_faults``) — or the run
must read ``none`` with a chip below the pole size it states it could not have seen.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from identification.gap.data import TouchData
from identification.gap.simlog import Timing
from identification.gap.step_ball import MIN_SIDE
from identification.identifiability import nominal_centres
from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict

SUFFIX = "+scatter"
STEP = "ball_step"
POLE = "pole_chip"
POLE_RANGE_UM = (8.0, 15.0)
SCATTER_URAD = 8.0
AFTER_LIMIT_SCATTER = 1.5
STEP_RANGE_UM = (5.0, 20.0)
STEP_SIZE_TOL_UM = 2.0


def split_scatter(scenario: str) -> tuple[str, bool]:
    """(base scenario, with indexing scatter?)."""
    if scenario.endswith(SUFFIX):
        return scenario[: -len(SUFFIX)], True
    return scenario, False


def scatter_scenarios(base: Sequence[str]) -> tuple[str, ...]:
    """The scattered variant of every base scenario, and the knocked ball."""
    return (*(f"{s}{SUFFIX}" for s in base), STEP, f"{POLE}{SUFFIX}")


def index_rms_um(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
                 sigma_urad: float) -> float:
    """RMS per observation (x, y, z, form; µm) of the centre scatter an index error of
    ``sigma_urad`` on every rotary axis causes on these poses (nominal chain)."""
    c = nominal_centres(machine, artefact, list(poses))
    layout = Layout((), len(artefact.balls))
    h = 1e-3
    var = 0.0
    for k in range(2):
        moved = Centres(c.pose, c.ball, c.b_deg + (h if k == 0 else 0.0),
                        c.c_deg + (h if k == 1 else 0.0), c.xyz_mm)
        q, _ = predict(machine, artefact, layout, np.zeros(layout.size), moved)
        d_um_per_urad = (q - c.xyz_mm) * 1e3 / (np.deg2rad(h) * 1e6)
        var += float(np.sum(d_um_per_urad**2)) / (4 * len(c))
    return float(np.sqrt(var) * sigma_urad)


@dataclass(frozen=True)
class KnockedBall:
    ball: int
    after_pose: int  # the last pose before the step
    vector_mm: np.ndarray
    t_s: float

    @property
    def size_um(self) -> float:
        return float(np.linalg.norm(self.vector_mm) * 1e3)


def knock(rng: np.random.Generator, n_balls: int, n_poses: int, timing: Timing | None = None
          ) -> KnockedBall:
    """A random ball knocked by 5-20 µm in a random direction between two poses, with at
    least ``MIN_SIDE`` visits on each side (``simlog.simulate``'s order and timing)."""
    timing = timing or Timing()
    ball = int(rng.integers(n_balls))
    after = int(rng.integers(MIN_SIDE - 1, n_poses - MIN_SIDE))
    v = rng.normal(size=3)
    v *= rng.uniform(*STEP_RANGE_UM) * 1e-3 / np.linalg.norm(v)
    nxt = after + 1  # the first touch of the next pose: simlog's clock
    t = nxt * n_balls * 5 * timing.touch_s + nxt * timing.pose_s + nxt * n_balls * timing.ball_s
    return KnockedBall(ball, after, v, float(t) - 0.5 * timing.pose_s)


def step_named(rep: dict, knocked: KnockedBall, ids: list[str]) -> bool:
    """Is the knocked ball named: ball, moment within one pose, size within the tolerance?"""
    s = rep.get("ball_step")
    return bool(rep["verdict"]["effect"] == "ball_moved" and s is not None
                and s["ball"] == ids[knocked.ball]
                and abs(s["after_pose"] - knocked.after_pose) <= 1
                and abs(s["size_um"] - knocked.size_um) <= STEP_SIZE_TOL_UM)


@dataclass(frozen=True)
class PoleChip:
    pose: int
    ball: int
    size_um: float


def chip_pole(rng: np.random.Generator, data: TouchData, n_balls: int) -> PoleChip:
    """Move the pole touch (5) of a random ball visit of ``data`` 8-15 µm against its approach
    (the probe switched early on a chip), in place."""
    chip = PoleChip(int(rng.integers(int(data.pose.max()) + 1)), int(rng.integers(n_balls)),
                    float(rng.uniform(*POLE_RANGE_UM)))
    k = np.flatnonzero((data.pose == chip.pose) & (data.ball == chip.ball)
                       & (data.touch == 5))[0]
    data.xyz_mm[k] -= chip.size_um * 1e-3 * data.direction[k]
    return chip


def chip_named(rep: dict, chip: PoleChip, ids: list[str]) -> bool:
    """Named at its visit (an outlier, or the pole defect the gap is consistent with), or the
    run reads ``none`` and states a pole size it could not have seen above the chip's."""
    v, at = rep["verdict"]["effect"], (chip.pose, ids[chip.ball])
    if v == "measurement_outlier":
        return [(o["pose"], o["ball"], o["touch"]) for o in rep["outliers"]] == [(*at, 5)]
    if v == "pole_defect":
        return (rep["pole_defect"]["pose"], rep["pole_defect"]["ball"]) == at
    pole = (rep["outlier_test"].get("min_chip_um") or {}).get("pole")
    return v == "none" and pole is not None and chip.size_um < pole
